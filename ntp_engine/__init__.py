"""ntp engine: the headless, bpy-free core of neural trace photography.

The package tree is the data flow; each subpackage imports only those before it:

    io -> scanner -> physics -> learn -> fit -> pipeline -> sim -> bench, cli

``io`` files and plumbing; ``scanner`` the device (record, camera, pattern, device file);
``physics`` frames, GGX, lumitexels, Eq. 1 and Eq. 6; ``learn`` synthetic traces, the network,
training and inference; ``fit`` GGX from lumitexels and albedo from pixels; ``pipeline`` a scan
folder to maps (``ntp reconstruct``); ``sim`` the virtual scanner, evaluation and the demo.
Conventions: ``docs/conventions.md``; the layout and its rules: ``docs/architecture.md``.
"""

__version__ = "0.1.0"
