"""Operators of the NTP panel. Each reports errors in Blender's report area (one line naming the
file) and leaves the file consistent: inputs are validated before any datablock is created.

Reconstruct runs ``ntp reconstruct`` in a separate process (the engine's cache makes a cancelled run
resumable): modal with a timer in the UI; the child writes its progress as JSON lines to a file
(``ntp ... --progress FILE``, ``ntp_engine.io.progress``), read each tick into the operator's progress,
the status bar and ``scene.ntp`` (stage, percent, time left); ESC cancels. In background mode (no
event loop) it waits for the process instead.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import bpy
from bpy_extras.io_utils import ImportHelper

from ntp_engine.io.errors import NtpInputError, error_line
from ntp_engine.io.progress import read_progress
from ntp_engine.scanner.scan_folder import load_poses, load_scan

from . import material
from . import scene as bscene
from .preferences import engine_options


def _settings(context):
    return context.scene.ntp


def _abs(path: str) -> Path:
    return Path(bpy.path.abspath(path)) if path else Path()


def _load_scan(context):
    s = _settings(context)
    if not s.scan_folder:
        raise NtpInputError(None, "set the scan folder first")
    return load_scan(_abs(s.scan_folder), device_file=_abs(s.device) if s.device else None)


def result_folder(context) -> Path:
    """The result folder: the setting, else ``<scan>_result`` beside the scan folder."""
    s = _settings(context)
    if s.result_folder:
        return _abs(s.result_folder)
    scan = _abs(s.scan_folder)
    return scan.parent / f"{scan.name.rstrip('/') or 'scan'}_result"


def _target_object(context):
    """The selected active mesh (an active object left unselected is no choice), else None."""
    obj = context.active_object
    return obj if obj is not None and obj.type == "MESH" and obj.select_get() else None


def _needs_scan(cls, context) -> bool:
    if not _settings(context).scan_folder:
        cls.poll_message_set("set the scan folder first")
        return False
    return True


def _idle(cls) -> bool:
    if any(p.poll() is None for p in _CHILDREN):
        cls.poll_message_set("an NTP run is in progress (ESC cancels it)")
        return False
    return True


class NTP_OT_import_mesh(bpy.types.Operator):
    """Import the scan's pre-scanned mesh (coordinates unchanged: z up, metres)"""

    bl_idname = "ntp.import_mesh"
    bl_label = "Import mesh"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        """Needs a scan folder."""
        return _needs_scan(cls, context)

    def execute(self, context):
        """Import the scan's mesh."""
        try:
            scan = _load_scan(context)
        except NtpInputError as err:
            self.report({"ERROR"}, str(err))
            return {"CANCELLED"}
        before = set(bpy.data.objects)
        if scan.mesh_path.suffix.lower() == ".ply":
            bpy.ops.wm.ply_import(filepath=str(scan.mesh_path), forward_axis="Y", up_axis="Z")
        else:
            bpy.ops.wm.obj_import(filepath=str(scan.mesh_path), forward_axis="Y", up_axis="Z")
        new = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
        if not new:
            self.report({"ERROR"}, f"{scan.mesh_path}: no mesh could be imported")
            return {"CANCELLED"}
        for o in new:
            o["ntp_scan"] = str(scan.folder)
        context.view_layer.objects.active = new[0]
        self.report({"INFO"}, f"imported {scan.mesh_path.name}")
        return {"FINISHED"}


_CHILDREN: set[subprocess.Popen] = set()  # engine processes running for this Blender session


def stop_child(proc: subprocess.Popen) -> None:
    """Stop an engine child: SIGINT (the engine removes its temporary files and exits 130; on
    Windows terminate), killed if it has not exited within 10 s (the next run removes what it left)."""
    if proc.poll() is None:
        if sys.platform == "win32":
            proc.terminate()
        else:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    _CHILDREN.discard(proc)


@bpy.app.handlers.persistent
def stop_children(*_args) -> None:
    """Stop every running engine child (handler for loading another file; also at exit)."""
    for proc in list(_CHILDREN):
        stop_child(proc)


def _interruptible() -> None:  # in the child, before the engine starts
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # Blender started from a background job ignores SIGINT


def spawn_engine(args: list[str], progress_file: Path) -> subprocess.Popen:
    """``ntp ARGS --quiet --progress FILE`` in a child process that sees the packages Blender sees
    (extension wheels) and stops cleanly on SIGINT (``stop_child``); registered in ``_CHILDREN``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    cmd = [sys.executable, "-m", "ntp_engine.cli", *args, "--quiet", "--progress", str(progress_file)]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        bufsize=1,
        env=env,
        preexec_fn=_interruptible if sys.platform != "win32" else None,
    )
    _CHILDREN.add(proc)
    return proc


def is_cancel(event) -> bool:
    """ESC pressed (a release, or any other key, does not cancel)."""
    return event.type == "ESC" and event.value == "PRESS"


def progress_status(record: dict) -> tuple[str, float]:
    """(status line, percent) for one progress record of the engine: stage, percent, time left."""
    total, done = record.get("total"), record.get("done", 0)
    percent = 100.0 * done / total if total else 0.0
    eta = record.get("eta_s")
    left = f", {eta:.0f} s left" if eta is not None and done < (total or 0) else ""
    return f"{record.get('stage', '')}: {percent:.0f}%{left}", percent


class _EngineProcess:
    """An ``ntp`` command in a child process: modal with a timer in the UI (progress from its JSON
    lines, ESC interrupts it), waited for in background mode. Subclasses give ``_command`` (the
    arguments after ``ntp``) and ``_succeeded``."""

    _proc = None
    _timer = None
    _reader = None
    _progress_file: Path | None = None
    _progress_offset = 0

    def _command(self, context) -> list[str]:
        raise NotImplementedError

    def _succeeded(self, context, stdout: str) -> str:
        """Act on a finished child; returns the status line."""
        raise NotImplementedError

    def _start(self, context) -> bool:
        try:
            _load_scan(context)  # fail here, in the report area, rather than in the child
        except NtpInputError as err:
            self.report({"ERROR"}, str(err))
            return False
        self._lines: list[str] = []
        fd, name = tempfile.mkstemp(prefix="ntp-progress-", suffix=".jsonl")
        os.close(fd)
        self._progress_file, self._progress_offset = Path(name), 0
        self._proc = spawn_engine(self._command(context), self._progress_file)

        def read():  # stderr holds only errors (--quiet): keep its lines for the report
            for line in self._proc.stderr:
                if line.strip():
                    self._lines.append(line.strip())

        self._reader = threading.Thread(target=read, daemon=True)
        self._reader.start()
        return True

    def _poll_progress(self, context) -> None:
        records, self._progress_offset = read_progress(self._progress_file, self._progress_offset)
        if records:
            s = _settings(context)
            s.status, s.progress = progress_status(records[-1])

    def _finish(self, context) -> set[str]:
        out = self._proc.stdout.read()  # stderr belongs to the reader thread (communicate() would race it)
        self._proc.wait()
        _CHILDREN.discard(self._proc)
        self._reader.join(timeout=5)
        if self._progress_file is not None:
            self._progress_file.unlink(missing_ok=True)
        s = _settings(context)
        if self._proc.returncode != 0:
            errors = [ln for ln in self._lines if "error" in ln.lower()] or self._lines[-1:] or ["failed"]
            s.status = errors[-1]
            self.report({"ERROR"}, errors[-1])
            return {"CANCELLED"}
        try:
            s.status, s.progress = self._succeeded(context, out), 100.0
        except (NtpInputError, OSError) as err:
            s.status = error_line(err)
            self.report({"ERROR"}, s.status)
            return {"CANCELLED"}
        self.report({"INFO"}, s.status)
        return {"FINISHED"}

    def execute(self, context):  # background mode: no event loop, wait for the child
        if not self._start(context):
            return {"CANCELLED"}
        return self._finish(context)

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        if not self._start(context):
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.25, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        wm = context.window_manager
        if is_cancel(event):
            stop_child(self._proc)
            self._cleanup(context)
            _settings(context).status = "cancelled (a re-run resumes from the last finished stage)"
            self.report({"WARNING"}, _settings(context).status)
            return {"CANCELLED"}
        if event.type == "TIMER":
            self._poll_progress(context)
            wm.progress_update(int(_settings(context).progress))
            context.workspace.status_text_set(f"NTP {self.bl_label} — {_settings(context).status} (ESC to cancel)")
            for area in context.screen.areas:
                area.tag_redraw()
            if self._proc.poll() is not None:
                self._cleanup(context)
                return self._finish(context)
        return {"PASS_THROUGH"}

    def cancel(self, context) -> None:
        """Blender ends the operator (another file loaded, quit): stop the child, tidy up."""
        if self._proc is not None:
            stop_child(self._proc)
        self._cleanup(context)

    def _cleanup(self, context) -> None:
        if self._progress_file is not None:
            self._progress_file.unlink(missing_ok=True)
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
        wm.progress_end()
        context.workspace.status_text_set(None)


def _engine_args(context) -> list[str]:
    """Arguments shared by register and reconstruct: scan, result, device, COLMAP model, and the
    preferences' threads and cache location."""
    s, opts = _settings(context), engine_options(context)
    out = result_folder(context)
    args = [str(_abs(s.scan_folder)), "--out", str(out)]
    if s.device:
        args += ["--device", str(_abs(s.device))]
    if s.colmap_folder:
        args += ["--colmap", str(_abs(s.colmap_folder))]
    if opts.threads:
        args += ["--threads", str(opts.threads)]
    cache = opts.cache_for(out)
    return args + (["--cache", str(cache)] if cache is not None else [])


class NTP_OT_register_photos(_EngineProcess, bpy.types.Operator):
    """Camera poses for the scan's photos (its poses file, else the marker board it names, else
    structure-from-motion; then aligned to the mesh) in a background process, then a camera object
    per photo with the photo as background"""

    bl_idname = "ntp.register_photos"
    bl_label = "Register photos"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        """Needs a scan folder and no engine run in progress."""
        return _needs_scan(cls, context) and _idle(cls)

    def _command(self, context) -> list[str]:
        return ["register", *_engine_args(context)]

    def _succeeded(self, context, stdout: str) -> str:
        scan = _load_scan(context)
        poses = load_poses(result_folder(context) / "poses.json")
        coll = bpy.data.collections.get("NTP Cameras")
        if coll is None:
            coll = bpy.data.collections.new("NTP Cameras")
            context.scene.collection.children.link(coll)
        for o in list(coll.objects):  # re-registering replaces the cameras (and their data)
            data = o.data
            bpy.data.objects.remove(o, do_unlink=True)
            if data is not None and data.users == 0:
                bpy.data.cameras.remove(data)
        # the photos' frame, so their background images are not stretched (sensor fit: horizontal)
        render = context.scene.render
        render.resolution_x, render.resolution_y = scan.scanner.width, scan.scanner.height
        render.resolution_percentage, render.pixel_aspect_x, render.pixel_aspect_y = 100, 1.0, 1.0
        for name in sorted(poses):
            cam = bscene.camera_object(f"NTP {name}", scan.scanner, poses[name], coll)
            img = bpy.data.images.load(str(scan.photos_dir / name), check_existing=True)
            cam.data.show_background_images = True
            cam.data.background_images.new().image = img
            cam.data.display_size = 0.02
        return stdout.strip().splitlines()[-1] if stdout.strip() else f"{len(poses)} photos registered"


class NTP_OT_reconstruct(_EngineProcess, bpy.types.Operator):
    """Reconstruct texture maps from the scan in a background process (ESC cancels; a re-run resumes)"""

    bl_idname = "ntp.reconstruct"
    bl_label = "Reconstruct"

    @classmethod
    def poll(cls, context):
        """Needs a scan folder and no engine run in progress."""
        return _needs_scan(cls, context) and _idle(cls)

    def _command(self, context) -> list[str]:
        s = _settings(context)
        model = s.model or engine_options(context).model
        return ["reconstruct", *_engine_args(context), "--resolution", str(s.resolution), "--model", model]

    def _succeeded(self, context, stdout: str) -> str:
        s = _settings(context)
        if not s.result_folder:
            s.result_folder = str(result_folder(context))
        return stdout.strip().splitlines()[-1] if stdout.strip() else "done"


def _build_materials(op, context, folder: Path, obj=None) -> set[str]:
    """Both materials of result ``folder`` on ``obj`` (``None``: the result's mesh, imported), the
    mesh made active; a bad folder, or an ``obj`` without the result's UVs, is one report and
    creates nothing (checked before anything is)."""
    try:
        ri = material.read_result(folder)
        if obj is not None and not material.carries_result_uvs(obj, ri.mesh):
            raise NtpInputError(
                None,
                f"the active mesh '{obj.name}' does not carry the result's UVs (its maps are laid out on "
                f"{folder / 'mesh.obj'}): select that mesh, or deselect everything to import it",
            )
        obj = obj or material.import_result_mesh(folder)
        p, a = material.build_materials(folder, obj, _settings(context).variant)
    except (NtpInputError, OSError) as err:
        op.report({"ERROR"}, error_line(err))
        return {"CANCELLED"}
    context.view_layer.objects.active = obj
    op.report({"INFO"}, f"built {p.name} and {a.name} on {obj.name}")
    return {"FINISHED"}


class NTP_OT_build_material(bpy.types.Operator):
    """Build the NTP materials (accurate + Principled) from the result folder on the active mesh
    (imports the result's mesh if none is selected)"""

    bl_idname = "ntp.build_material"
    bl_label = "Build material"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        """Needs a result folder (what is in it is checked when run, with the reason reported)."""
        if not result_folder(context).is_dir():
            cls.poll_message_set("reconstruct first (or set a result folder)")
            return False
        return True

    def execute(self, context):
        """Build both materials from the result folder on the active (or imported) mesh."""
        return _build_materials(self, context, result_folder(context), _target_object(context))


class NTP_OT_relight_preview(bpy.types.Operator):
    """A Cycles look-dev scene around the active object: camera, key/fill/rim lights, optional turntable"""

    bl_idname = "ntp.relight_preview"
    bl_label = "Relight preview"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        """Needs an active mesh."""
        if _target_object(context) is None:
            cls.poll_message_set("select the mesh to light")
            return False
        return True

    def execute(self, context):
        """Build the look-dev rig around the active mesh."""
        obj = _target_object(context)
        if obj is None:
            self.report({"ERROR"}, "select the mesh to light first")
            return {"CANCELLED"}
        rig = bscene.relight_rig(obj, turntable_frames=_settings(context).turntable_frames)
        if context.window is not None:  # show it; the user's scene stays as it was, one click away
            context.window.scene = rig["scene"]
        self.report({"INFO"}, f"relight rig ready in scene '{rig['scene'].name}' (render with F12)")
        return {"FINISHED"}


class _FolderImport(ImportHelper):
    """File → Import of a folder: the file browser picks a directory (``self.directory``)."""

    bl_options = {"REGISTER", "UNDO"}
    directory: bpy.props.StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN"})
    filename_ext = ""
    use_filter_folder = True


class NTP_OT_import_result(_FolderImport, bpy.types.Operator):
    """Import an NTP result folder: its mesh with both materials (File → Import)"""

    bl_idname = "import_scene.ntp_result"
    bl_label = "Import NTP result"

    def execute(self, context):
        """Check the folder, import its mesh, build the materials, remember it as the result."""
        done = _build_materials(self, context, Path(self.directory))
        if done == {"FINISHED"}:
            _settings(context).result_folder = str(Path(self.directory))
        return done


class NTP_OT_import_colmap(_FolderImport, bpy.types.Operator):
    """Register the scan's photos from an existing COLMAP model folder (no SfM) and add the
    cameras (File → Import; needs the scan folder set in the NTP panel)"""

    bl_idname = "import_scene.ntp_colmap"
    bl_label = "Import COLMAP model as NTP cameras"

    @classmethod
    def poll(cls, context):
        """Needs a scan folder (the photos the model registered) and no run in progress."""
        return _needs_scan(cls, context) and _idle(cls)

    def execute(self, context):
        """Register with the model: the engine aligns it to the mesh and checks it on the photos."""
        _settings(context).colmap_folder = self.directory
        return bpy.ops.ntp.register_photos("INVOKE_DEFAULT")


def menu_import(self, context) -> None:
    """File → Import entries."""
    self.layout.operator(NTP_OT_import_result.bl_idname, text="NTP result (folder)")
    self.layout.operator(NTP_OT_import_colmap.bl_idname, text="COLMAP model as NTP cameras (folder)")


CLASSES = (
    NTP_OT_import_result,
    NTP_OT_import_colmap,
    NTP_OT_import_mesh,
    NTP_OT_register_photos,
    NTP_OT_reconstruct,
    NTP_OT_build_material,
    NTP_OT_relight_preview,
)
