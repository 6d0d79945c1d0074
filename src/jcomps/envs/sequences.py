"""The paper's task sequences (appendix A), verbatim, and our held-out sets."""

# Ant Goal and Ant Direction: angles in degrees (0 = +x, 90 = +y). Point Goal reuses them for its goals.
ANT_ANGLES_DEG = (
    -171, 9, -162, 18, -153, 27, -144, 36, -135, 45, -126, 54, -117, 63, -108, 72, -99, 81, -90, 90,
    -81, 99, -72, 108, -63, 117, -54, 126, -45, 135, -36, 144, -27, 153, -18, 162, -9, 171, 0, 180,
)

# Half-Cheetah Velocity: goal velocities along x in m/s.
CHEETAH_VELOCITIES = (
    -2.66, 0.14, -2.52, 0.28, -2.38, 0.42, -2.24, 0.56, -2.1, 0.7, -1.96, 0.84, -1.82, 0.98, -1.68, 1.12,
    -1.54, 1.26, -1.4, 1.4, -1.26, 1.54, -1.12, 1.68, -0.98, 1.82, -0.84, 1.96, -0.7, 2.1, -0.56, 2.24,
    -0.42, 2.38, -0.28, 2.52, -0.14, 2.66, 0.0, 2.8,
)

# Held-out tasks (our choice): never in the training lists. The paper's angles are every multiple of 9
# degrees in (-180, 180], so held-out angles sit between them; the held-out velocities sit between the
# paper's multiples of 0.14 m/s.
HELD_OUT_ANGLES_DEG = (-157.5, -112.5, -67.5, -22.5, 22.5, 67.5, 112.5, 157.5)
HELD_OUT_VELOCITIES = (-2.59, -1.89, -1.19, -0.49, 0.49, 1.19, 1.89, 2.59)
