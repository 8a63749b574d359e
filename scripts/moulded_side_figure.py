"""Draw docs/moulded-side.png: the moulded surface, the thickness and the face the sensor sees.

Run: ``.venv/bin/python scripts/moulded_side_figure.py [OUT.png]`` (matplotlib, no display needed).
A section through a curved plate, exaggerated: left laid moulded side up, right turned over
(moulded side down), where the analysis offsets the design by the thickness and turns it over.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

T_MM = 15.0
R_MM = 900.0  # exaggerated curvature, so both faces read apart


def _faces(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Moulded face z = x^2 / 2R (normals up, away from the material) and the other face T below it."""
    z = x**2 / (2 * R_MM)
    n = np.column_stack([-x / R_MM, np.ones_like(x)])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return x, z, x - T_MM * n[:, 0], z - T_MM * n[:, 1]


def draw(out: Path) -> Path:
    fig = Figure(figsize=(10, 4.2), dpi=110)
    x = np.linspace(-300, 300, 121)
    mx, mz, ox, oz = _faces(x)
    cases = (
        ("design_side = moulded_up: the sensor sees the design", False),
        ("design_side = moulded_down: the plate turned over", True),
    )
    for k, (title, turned) in enumerate(cases):
        ax = fig.add_subplot(1, 2, k + 1)
        sign = -1.0 if turned else 1.0  # a half turn about the plate's x axis: (x, z) -> (-x, -z)
        lift = 80.0 if turned else 0.0
        m = (sign * mx, sign * mz + lift)
        o = (sign * ox, sign * oz + lift)
        ax.fill(np.r_[m[0], o[0][::-1]], np.r_[m[1], o[1][::-1]], color="0.85", label="plate material")
        ax.plot(*m, color="tab:blue", lw=2.2, label="moulded face (the design file)")
        ax.plot(*o, color="tab:orange", lw=1.6, label="other face")
        seen = o if turned else m
        ax.plot(*seen, color="tab:red", lw=0.9, ls="--", label="face the sensor sees")
        # the thickness, along the normal at x = 150
        i = 95
        ax.annotate("", xy=(o[0][i], o[1][i]), xytext=(m[0][i], m[1][i]),
                    arrowprops={"arrowstyle": "<->", "color": "k", "lw": 0.8})  # fmt: skip
        ax.text(m[0][i] + 8, (m[1][i] + o[1][i]) / 2, f"t = {T_MM:g} mm", fontsize=8)
        # sensor rays from above
        top = max(seen[1].max(), m[1].max()) + 40
        for xs in (-200, 0, 200):
            j = int(np.argmin(np.abs(seen[0] - xs)))
            ax.annotate("", xy=(seen[0][j], seen[1][j]), xytext=(seen[0][j], top),
                        arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 0.7})  # fmt: skip
        ax.text(0, top + 4, "HD8 laser line", ha="center", fontsize=8, color="tab:red")
        ax.axhline(min(m[1].min(), o[1].min()) - 4, color="0.3", lw=3)
        if turned:
            ax.text(0, oz.min() * -1 + lift + 12, "design offset by t against its\nnormals, then turned over",
                    ha="center", fontsize=8)  # fmt: skip
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("along the plate (mm)")
        ax.set_ylabel("height (mm, curvature exaggerated)")
        ax.set_ylim(-30, 200)
        if k == 0:
            ax.legend(fontsize=7, loc="upper center")
    fig.tight_layout()
    fig.savefig(out, format="png")
    return out


if __name__ == "__main__":
    print(draw(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/moulded-side.png")))
