"""The forming tests' shared plate: the shipped coefficient table and a 1200 x 800 x 15 mm model."""

from __future__ import annotations

import pytest

from analysis.forming.coefficients import Coefficients, load_coefficients
from analysis.forming.plate_model import PlateModel

L_MM, W_MM, H_MM = 1200.0, 800.0, 15.0


@pytest.fixture(scope="session")
def table() -> Coefficients:
    return load_coefficients()


@pytest.fixture(scope="session")
def model(table: Coefficients) -> PlateModel:
    return PlateModel.build(L_MM, W_MM, H_MM, table.for_material("mild_steel"))
