"""The scanner: its record and radiometry (``scanner``), the camera model (``camera``), lighting
patterns (``pattern``) and the device file that stores a calibration (``device_file``)."""
