"""ntp engine: the headless, bpy-free core of neural trace photography.

Data flow and conventions: ``docs/`` and ../shared/DESIGN.md. Modules, in the order data flows:
``device`` (scanner calibration), ``frame`` and ``brdf`` (anisotropic GGX), ``lumitexel`` (the
network's output space), ``measurement`` (Eq. 1 and the confidence of Eq. 6).
"""
__version__ = "0.1.0"
