"""The scan pipeline: the scan folder (``scan_folder``), photo selection (``photo_selection``),
structure from motion (``sfm``) and its alignment to the mesh (``align``), texels of the UV atlas
(``texels``), trace assembly (``traces``), the fit stage (``fit_traces``), the result folder
(``result``), the stage cache (``cache``) and the stage runner behind ``ntp reconstruct``
(``stages``)."""
