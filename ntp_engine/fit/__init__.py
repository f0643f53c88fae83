"""Fitting anisotropic GGX (paper §7): the lobe's geometry from specular lumitexels
(``geometry``: a linear solve in A-space, then Levenberg-Marquardt), the unseen-highlight check
(``highlights``, Eq. 6 from the fit), RGB albedos from the trace's own pixels (``albedo``), and the
paper's per-texel L-BFGS-B as the benchmark baseline (``baseline``)."""
