"""Registration of the design surface to a measured plate: section 2.2 of the paper, one module per stage.

The design is read through a :class:`~analysis.register.height_field.HeightField` (the design mesh
rasterised once, :mod:`~analysis.register.height_field`); :mod:`~analysis.register.transforms` holds
the rigid-body helpers and :class:`~analysis.register.transforms.RegistrationError`. Three stages,
each a pure function returning a small result object:

1. :mod:`~analysis.register.coarse` -- the paper's boundary fit (2.2.1) from the corners;
2. :mod:`~analysis.register.icp` -- point-to-plane ICP (2.2.2) against the design surface;
3. :mod:`~analysis.register.onesided` -- the non-penetrating fit (2.2.3): the design rests on the
   plate like a worker's template, on :mod:`~analysis.register.rest_surface`'s estimate of the
   plate when the points are noisy.

:func:`analysis.register.fit.register` runs them (every corner shift, the best ICP, the one-sided
fit); :func:`analysis.register.fit.register_from_placement` starts from a nominal placement.
:mod:`~analysis.register.locate` places the design on the bed from a locate run's sparse cloud (a
2D fit of the design's outline to the plate's edges), before any scan.

Frames: every transform is a 4x4 homogeneous matrix in millimetres, ``T_meas_design`` maps design
coordinates into the measurement (robot base) frame. The deflection direction is +z of the
measurement frame.
"""
