"""Files and shared plumbing, below every stage: one-line input errors, atomic writes, TOML input,
images (OpenImageIO), meshes, SVBRDF maps, Embree ray casting, asset paths and progress reports."""
