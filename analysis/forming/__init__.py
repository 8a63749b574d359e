"""Line-heating forming: the plate's response to heating lines (inherent-strain method on a
scikit-fem plate model) and the planner that turns a deviation into the next round's lines.
docs/forming.md describes the model, its assumptions and its checks."""
