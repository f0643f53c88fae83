"""The add-on's preferences (Edit → Preferences → Add-ons → NTP): the engine's model, its CPU
threads and where stage caches go. Saved with Blender's preferences, not with a .blend; the
scene's settings (``properties``) override the model where set."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import bpy

from ntp_engine.learn.models import DEFAULT_MODEL

PACKAGE = __package__ or "ntp_addon"  # "ntp_addon", or "bl_ext.<repository>.ntp" as an extension


@dataclass(frozen=True)
class EngineOptions:
    """What the preferences ask of an engine run: model name or folder, threads (0: every core),
    cache root (empty: each result keeps its cache inside)."""

    model: str = DEFAULT_MODEL
    threads: int = 0
    cache_root: str = ""

    def cache_for(self, result: Path) -> Path | None:
        """The stage cache for ``result``: ``None`` (inside it), else one folder per result under
        the root, named after it and its full path (two results named alike never share one)."""
        if not self.cache_root:
            return None
        key = hashlib.sha1(str(result.resolve()).encode()).hexdigest()[:8]
        return Path(bpy.path.abspath(self.cache_root)) / f"{result.name}-{key}"


class NTPPreferences(bpy.types.AddonPreferences):
    """Engine settings shared by every file."""

    bl_idname = PACKAGE

    model: bpy.props.StringProperty(
        name="Model",
        default=DEFAULT_MODEL,
        description="Shipped model name or a model folder (a scene's own Model setting overrides it)",
    )
    threads: bpy.props.IntProperty(
        name="CPU threads",
        default=0,
        min=0,
        max=1024,
        description="Threads an engine run uses (0: every core; fewer keeps Blender responsive)",
    )
    cache_root: bpy.props.StringProperty(
        name="Cache location",
        subtype="DIR_PATH",
        default="",
        description="Where stage caches go, one folder per result (empty: inside each result folder)",
    )

    def draw(self, context):
        """Lay out the preferences."""
        col = self.layout.column()
        for prop in ("model", "threads", "cache_root"):
            col.prop(self, prop)


def engine_options(context) -> EngineOptions:
    """The preferences as ``EngineOptions`` (defaults where the add-on is registered without
    Blender's add-on system, e.g. ``ntp_addon.register()`` in a script)."""
    addon = context.preferences.addons.get(PACKAGE)
    prefs = getattr(addon, "preferences", None)
    if prefs is None:
        return EngineOptions()
    return EngineOptions(prefs.model or DEFAULT_MODEL, prefs.threads, prefs.cache_root)


CLASSES = (NTPPreferences,)
