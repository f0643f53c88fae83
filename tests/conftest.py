"""bpy must be imported before torch (both bundle native libraries); do it once for the suite."""
try:
    import bpy  # noqa: F401
except ImportError:  # the engine's tests run without Blender
    bpy = None
