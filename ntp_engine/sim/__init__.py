"""Simulation and evaluation: the renderer (``renderer``), the virtual scanner that writes scan
folders with ground truth (``virtual_scan``), the demo asset (``demo_asset``), errors against the
truth (``evaluate``) and ``ntp demo`` (``demo``)."""
