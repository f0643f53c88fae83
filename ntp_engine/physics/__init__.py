"""The physics of a measurement: local frames (``frame``), the anisotropic GGX BRDF (``brdf``),
lumitexels (``lumitexel``), what the camera measures (``measurement``, paper Eq. 1) and how well a
trace saw a highlight (``confidence``, Eq. 6)."""
