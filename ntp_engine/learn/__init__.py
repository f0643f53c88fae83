"""Learning the reflectance from traces: synthetic training traces (``synthetic``), the trace
network with its lighting-pattern layer (``network``), training (``train``), the trace table
(``ragged``), batched inference (``inference``) and the shipped models (``models``)."""
