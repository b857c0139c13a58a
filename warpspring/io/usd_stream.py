"""How :class:`~warpspring.io.usd.UsdWriter` streams its frames to disk: the file's life from creation to the
packed file, resuming a stopped run's file, and what a failed save or a killed run leaves.

While a run writes ``out.usdc``, its frames live in a folder beside it, ``out.usdc.frames/``: the static prims
once (``static.usdc``), and each frame as its own small layer (``frame.001001.usdc``), written whole through a
temporary file and renamed, so a file is either absent or complete; every 100 frames they are gathered into a
chunk layer, and neighbouring chunks merge as they grow (up to 64 MB), so the stage has few clips at any frame
count. A frame whose accelerations come with the next frame is written again then under a new name
(``frame.001001.full.usdc``), and the root names it once it is saved (the first file goes after a grace period),
so a frame on disk is never rewritten in place. ``out.usdc`` itself is a small root layer, rewritten the same way after every frame: the stage's
metadata, the static layer as a sublayer, and the frames as value clips (a template of the frame files up to
the last one written). So at every moment the file is a valid stage holding every frame written: another
process can open it as often as it likes while the run goes on and never sees a torn file or the frame count
go backwards, and a run that is killed (even by SIGKILL) leaves every frame it wrote. Each frame costs the
same to write however many came before, for ``.usdc`` and ``.usda`` alike. On
:meth:`~warpspring.io.usd.UsdWriter.close` the frames are packed into one self-contained layer, renamed over
``out.usdc``, and the folder is removed. A small companion process removes USD's temporary files if the run
dies while one is being written, so a killed run leaves its file, its frames folder and nothing else.

A save that fails (a full disk, the file or its folder removed) raises
:class:`~warpspring.errors.OutputError`, one line naming the frame and the OS's reason (USD's own errors often
carry none, or quote it in words: the OS's reason is then given alone, "No space left on device [ENOSPC]",
without USD's noise after it such as "crate file corrupt" about the temporary file; else the file system is
examined for one). The file keeps every frame saved before it, a valid stage through its frames folder, and
the writer drops the unsaved frame instead of trying to save it again on close. The root's ``endTimeCode`` is
the last frame on disk at every moment (the start before the first frame is saved; after a failed save, the
last frame saved).

One run owns an output: the writer holds an advisory lock (``flock``) on ``out.usdc.lock`` beside the file,
which names its process (its PID is written in it), from before it reads or removes anything of the output until
the file is packed (:class:`~warpspring.io.output_lock.OutputLock`); the frames folder is only touched under it. A second writer of the same
output, in another process or this one, is refused with a ConfigError naming that process. The kernel releases
the lock when the process dies, however it dies, so a killed run leaves nothing stuck: the companion process
removes the lock file, and a lock file left without a holder is taken over by the next run. USD's own warnings
and errors while the file is written never reach stderr: they are trapped, and folded into the one-line error
of a failed save.

The writer defines the prims (:class:`~warpspring.io.usd_prims.UsdPrims`) and each frame's samples; this module
holds the frames folder, the clips, the root layer, packing, the companion process and the reasons of failures.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from typing import NamedTuple

import warp as wp

from ..errors import ConfigError, OutputError, os_error_reason
from ..version import __version__

_EXTENSIONS = (".usdc", ".usda", ".usd")


class UsdStream:
    """The file side of :class:`~warpspring.io.usd.UsdWriter`, its base: the frames folder and its reaper
    (:meth:`_open`), the static layer and the root (:meth:`_start`), each frame saved as a clip (:meth:`_append`),
    clips gathered into chunks, and the packed file (:meth:`close`).

    The writer sets ``model`` (its up axis), ``fps`` and ``start_frame`` and the pxr modules (``_Sdf``, ``_Vt``,
    ``_Gf``, ``_Tf``) before :meth:`_open`, builds ``stage`` (the static prims) between :meth:`_open` and
    :meth:`_start`, and registers every attribute it samples per frame with :meth:`_animate`.
    """

    def _open(self, path: str, ext: str) -> None:
        """Begin the file at ``path`` (a checked output path of extension ``ext``, whose :class:`~warpspring.io.output_lock.OutputLock` the
        writer holds): remove an earlier output there and its frames folder, create the frames folder and start
        the reaper.

        Raises:
            ConfigError: the frames folder cannot be created (with the OS's reason).
        """
        self.path = path
        self.parts = parts_folder(path)
        self.frame_count = 0
        self.frames_saved = 0  # frames on disk: 0 .. frames_saved - 1
        self._closed = False
        self._failed = False
        self._reaper = None
        self._format = ".usda" if ext == ".usda" else ".usdc"
        self._animated: list = []  # (attribute path, value type) of every attribute sampled per frame
        self._pending = None  # (time code, layer, the frame before's (time code, layer) if amended) being saved
        self._last_frame = None  # (time code, layer) of the last frame saved while it may still be amended
        self._keep_last = False  # keep the last frame out of chunks (its accelerations come with the next frame)
        self._clip_roots = getattr(self, "_clip_roots", ["/World"])  # the prims whose subtrees the clips hold
        self._clips: list[_Clip] = []  # the clip layers in the frames folder, in time order
        self._loose: list = []  # (time code, layer) of the saved frames not yet gathered into a chunk
        self._loose_bytes = 0  # their size on disk [B]
        self._obsolete: list = []  # (when [s, monotonic], paths) of frame files a chunk replaced, to remove
        try:
            _remove_output(path)
            os.makedirs(self.parts)
            self._reaper = _Reaper(path)
        except OSError as exc:
            self._release()
            reason = _reason(exc) or _diagnose(path) or "no reason given"
            raise ConfigError(f"cannot create the USD file {path!r}: {reason}") from None

    def _start(self, kept: list | None, keep_frames: int) -> None:
        """Write the static layer (``stage``'s root layer) and the clips' manifest into the frames folder, the
        ``keep_frames`` frames ``kept`` of a stopped run being resumed (:func:`read_frames`), then the root:
        from here on the file is a valid stage.

        Raises:
            ConfigError: something could not be written (what was written is removed).
        """
        said: list = []
        try:
            with self._Tf.DiagnosticTrap() as trap:
                try:
                    self._export(self.stage.GetRootLayer(), os.path.join(self.parts, STATIC_NAME))
                    self._export(self._manifest(), os.path.join(self.parts, MANIFEST_NAME))
                    if kept is not None:
                        self._write_kept(kept, keep_frames)
                    self._write_root()
                finally:
                    said = _trapped(trap)
        except (OSError, self._Tf.ErrorException) as exc:
            self._abandon()
            reason = _reason(exc, said) or _diagnose(self.path) or "USD gave no reason"
            code = getattr(exc, "errno", None) or _os_code(reason)
            if code in _OS_MESSAGES:  # the OS's reason alone, without USD's noise after it
                reason = os_error_reason(OSError(code, os.strerror(code)))
            raise ConfigError(f"cannot create the USD file {self.path!r}: {reason}") from None
        self.frames_saved = self.frame_count

    def _animate(self, attribute):
        """Record ``attribute`` (a Usd.Attribute of the static stage) as sampled per frame; its path."""
        path = attribute.GetPath()
        self._animated.append((path, attribute.GetTypeName()))
        return path

    @property
    def _types(self) -> dict:
        return dict(self._animated)

    def _time_code(self, frame: int) -> float:
        """The time code of frame ``frame``: ``start_frame`` + frame, or over an asset ``start_frame`` + frame ×
        its timeCodesPerSecond / fps (``_codes_per_second``; computed so, 3 × 24 / 60 is 1.2 exactly)."""
        codes = getattr(self, "_codes_per_second", None)
        return self.start_frame + (frame if codes is None else frame * codes / self.fps)

    def _frame_index(self, time_code: float) -> int:
        """The number in the file name of the frame at ``time_code``: ``start_frame`` + its frame."""
        codes = getattr(self, "_codes_per_second", None)
        frames = time_code - self.start_frame if codes is None else (time_code - self.start_frame) * self.fps / codes
        return self.start_frame + int(round(frames))

    def _append(self, samples: list, amend: list = ()) -> None:
        """Save one frame's samples, (attribute path, value) pairs, as the next frame: time code
        :meth:`_time_code` of :attr:`frame_count`. ``amend``: samples of the frame before (its accelerations, known
        now), added to its layer, which is written again (whole, renamed) before this frame's."""
        time_code = self._time_code(self.frame_count)
        amended = None
        if amend and self._last_frame is not None:
            before, layer = self._last_frame
            self._add_samples(layer, before, amend)
            amended = (before, layer)
        self._pending = (time_code, self._frame_layer(time_code, samples), amended)
        self.frame_count += 1
        self._save()

    def close(self) -> None:
        """Write the self-contained file (every frame in one layer at ``path``, the frames folder removed) and
        release the stage. Safe to call twice. After a failed save it only releases the stage: the file keeps
        the frames saved before the failure, in the frames folder beside it.

        Raises:
            OutputError: the file could not be written (the frames stay readable through the frames folder).
        """
        if self._closed:
            return
        try:
            if not self._failed:
                self._pack()
        finally:
            self._release()

    def __enter__(self) -> UsdStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- saving ---------------------------------------------------------------------------------------

    def _save(self) -> None:
        """Save the pending frame: its layer into the frames folder, then the root layer that makes it part of
        the stage. A failure releases the writer and raises OutputError; the file keeps the frames before."""
        frames = self.frame_count
        said: list = []
        try:
            with self._Tf.DiagnosticTrap() as trap:  # USD's warnings go into the error, not to stderr
                try:
                    saved = self._save_layer()
                    if saved is not False:
                        old = self._swap_amended() if self._pending[2] is not None else []
                        self._add_clip(*self._pending)
                        self._write_root()
                        if old:  # only now: a reader (or the root left by a kill) named it until here
                            self._obsolete.append((time.monotonic() + _GRACE, old))
                            self._reaper.obsolete(old)
                finally:
                    said = _trapped(trap)
        except (OSError, self._Tf.ErrorException) as exc:
            reason, code = _reason(exc, said), getattr(exc, "errno", None)
        else:
            if saved is not False:
                self.frames_saved = frames
                self._pending = None
                with self._Tf.DiagnosticTrap() as trap:  # a chunk that fails leaves the clips as they were
                    try:
                        self._gather()
                    finally:
                        _trapped(trap)
                return
            reason, code = "; ".join(said), None  # USD refused, perhaps with a warning
        if code is None:  # USD quotes an OS error in words only ("No space left on device"): that reason alone
            code = _os_code(reason)
            if code is not None:
                reason = os_error_reason(OSError(code, os.strerror(code)))
        if code is None:  # no OS error: say what the file system shows (a full disk: the OS's reason alone)
            diagnosis = _diagnose(self.path)
            if diagnosis.endswith(_FULL_DISK):
                code, reason = errno.ENOSPC, os_error_reason(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
            else:
                reason = f"{reason} ({diagnosis})" if reason and diagnosis else reason or diagnosis
        reason = reason or "USD gave no reason (a full disk, or the file or its folder removed?)"
        saved = self.frames_saved
        lost = frames - saved
        what = f"frame {saved}" if lost == 1 else f"frames {saved}..{frames - 1}"
        held = f"frames 0..{saved - 1}" if saved > 1 else "frame 0" if saved == 1 else "no frame"
        self._failed = True
        self._release()  # the unsaved frame is dropped: the file keeps what was saved
        raise OutputError(f"cannot write {what} to the USD file {self.path!r}: {reason}; the file holds {held}",
                          path=self.path, frame=saved, frames_saved=saved, code=code)

    def _save_layer(self) -> bool:
        """Write the pending frame's layer into the frames folder: whether USD saved it (it may also raise
        OSError or Tf.ErrorException)."""
        time_code, layer, amended = self._pending
        if amended is not None:  # under a new name: a failed write never touches the frame saved before
            if self._export(amended[1], os.path.join(self.parts, self._frame_file(amended[0], amended=True))) is False:
                return False
        return self._export(layer, os.path.join(self.parts, self._frame_file(time_code)))

    def _frame_file(self, time_code: float, *, amended: bool = False) -> str:
        """The file name of the frame at ``time_code`` (``amended``: once its accelerations are added)."""
        return frame_name(self._frame_index(time_code), (".full" if amended else "") + self._format)

    def _swap_amended(self) -> list:
        """After a save: the clip of the frame before names its amended file; returns its first file, to remove
        after a grace period once the root that names the amended one is written."""
        time_code, _ = self._pending[2]
        clip = self._clips[-1]
        name = self._frame_file(time_code, amended=True)
        self._clips[-1] = clip._replace(name=name, size=os.path.getsize(os.path.join(self.parts, name)))
        return [os.path.join(self.parts, clip.name)]

    def _export(self, layer, path: str) -> bool:
        """Write ``layer`` to ``path`` whole (USD writes a temporary file and renames it: a reader sees the
        old file or the new one, never a part)."""
        return layer.Export(path)

    def _add_clip(self, time_code: float, layer, amended=None) -> None:
        """Count a frame saved in the frames folder as a clip of the stage, and keep its layer for its chunk."""
        self._last_frame = (time_code, layer)
        name = self._frame_file(time_code)
        size = os.path.getsize(os.path.join(self.parts, name))
        self._clips.append(_Clip(time_code, time_code, name, -1, size))
        self._loose.append((time_code, layer))
        self._loose_bytes += size

    def _gather(self) -> None:
        """Keep the clips few, so that rewriting the root and opening the stage cost the same at any frame: the
        loose frames go into a chunk layer once they are many or large, and two neighbouring chunks of one
        level merge into one of the next level while together they stay below ``_CHUNK_BYTES`` (a binary
        counter: about log2 of the frames' chunks, plus one per ``_CHUNK_BYTES`` of frames). Frame and chunk
        files a merge replaced are removed ``_GRACE`` seconds later."""
        now = time.monotonic()
        while self._obsolete and self._obsolete[0][0] <= now:  # readers had _GRACE seconds to finish with them
            for path in self._obsolete.pop(0)[1]:
                try:
                    os.remove(path)
                except OSError:
                    pass
        keep = 1 if self._keep_last and self._loose else 0  # the last frame waits for its accelerations
        if len(self._loose) - keep < _CHUNK_FRAMES and self._loose_bytes < _CHUNK_BYTES:
            return
        loose, self._loose = self._loose[: len(self._loose) - keep], self._loose[len(self._loose) - keep:]
        self._loose_bytes = 0
        if len(loose) >= 2:
            chunk = self._Sdf.Layer.CreateAnonymous(self._format)
            for _, layer in loose:
                self._copy_samples(layer, chunk)
            if not self._replace_clips(len(loose), chunk, level=0, skip=keep):
                return
        while len(self._clips) >= 2 + keep:
            a, b = self._clips[len(self._clips) - keep - 2: len(self._clips) - keep]
            if a.level < 0 or a.level != b.level or a.size + b.size > _CHUNK_BYTES:
                return
            merged = self._Sdf.Layer.CreateAnonymous(self._format)
            for clip in (a, b):
                self._copy_samples(self._Sdf.Layer.OpenAsAnonymous(os.path.join(self.parts, clip.name)), merged)
            if not self._replace_clips(2, merged, level=a.level + 1, skip=keep):
                return

    def _replace_clips(self, count: int, layer, *, level: int, skip: int = 0) -> bool:
        """Write ``layer`` as one chunk in place of ``count`` clips (the last ones but ``skip``), then the root that
        uses it; whether it worked (if not, the clips stay as they were: the file is as valid)."""
        end = len(self._clips) - skip
        replaced = self._clips[end - count: end]
        first, last = replaced[0].first, replaced[-1].last
        name = chunk_name(self._frame_index(first), self._frame_index(last), self._format)
        path = os.path.join(self.parts, name)
        clips = self._clips
        try:
            self._export(layer, path)
            self._clips = clips[:end - count] + [_Clip(first, last, name, level, os.path.getsize(path))] + clips[end:]
            self._write_root()
        except (OSError, self._Tf.ErrorException):
            self._clips = clips
            return False
        old = [os.path.join(self.parts, clip.name) for clip in replaced]
        self._obsolete.append((time.monotonic() + _GRACE, old))
        self._reaper.obsolete(old)
        return True

    def _copy_samples(self, source, target) -> None:
        """Copy every animated attribute's samples of layer ``source`` into layer ``target``."""
        Sdf = self._Sdf
        for attribute, value_type in self._animated:
            if not source.GetAttributeAtPath(attribute):
                continue
            if not target.GetAttributeAtPath(attribute):
                prim = Sdf.CreatePrimInLayer(target, attribute.GetPrimPath())
                Sdf.AttributeSpec(prim, attribute.name, value_type, Sdf.VariabilityVarying)
            for time_code in source.ListTimeSamplesForPath(attribute):
                target.SetTimeSample(attribute, time_code, source.QueryTimeSample(attribute, time_code))

    def _write_root(self) -> None:
        """Write the root layer at :attr:`path`: the stage's metadata, the static layer as a sublayer and the
        saved frames as value clips (chunks of frames, then the latest frames one by one)."""
        Sdf, Vt, Gf = self._Sdf, self._Vt, self._Gf
        layer = Sdf.Layer.CreateAnonymous(self._format)
        last = self._clips[-1].last if self._clips else self.start_frame  # the last frame on disk
        self._stage_metadata(layer, end=last)
        folder = os.path.basename(self.parts)
        layer.subLayerPaths.append(f"./{folder}/{STATIC_NAME}")
        over = getattr(self, "_layer", None)
        if over is not None:  # the asset, sublayered or referenced
            over.author_arc(layer)
        for root in self._clip_roots if self._clips else ():
            spec = layer.GetPrimAtPath(root) or Sdf.CreatePrimInLayer(layer, root)
            spec.specifier = Sdf.SpecifierOver
            start = float(self.start_frame)
            spec.SetInfo("clips", {"default": {
                "assetPaths": Sdf.AssetPathArray([Sdf.AssetPath(f"./{folder}/{c.name}") for c in self._clips]),
                "active": Vt.Vec2dArray([Gf.Vec2d(float(c.first), float(i)) for i, c in enumerate(self._clips)]),
                "times": Vt.Vec2dArray([Gf.Vec2d(start, start), Gf.Vec2d(float(last), float(last))]),
                "primPath": root,
                "manifestAssetPath": Sdf.AssetPath(f"./{folder}/{MANIFEST_NAME}"),
                "interpolateMissingClipValues": True,  # a stopped world holds its last sample
            }})
        self._export(layer, self.path)

    def _stage_metadata(self, layer, *, end: float) -> None:
        """Author what DCC tools need to play the file (USD's fallbacks are wrong for simulation caches); over an
        asset, the asset's metadata."""
        layer.startTimeCode = float(self.start_frame)
        layer.endTimeCode = float(end)
        layer.customLayerData = {"generator": f"warpspring {__version__} (warp {wp.__version__})"}
        if getattr(self, "_layer", None) is not None:
            self._layer.stage_metadata(layer)
            return
        layer.defaultPrim = "World"
        layer.pseudoRoot.SetInfo("upAxis", self.model.up_axis)
        layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
        layer.timeCodesPerSecond = self.fps
        layer.framesPerSecond = self.fps

    def _manifest(self):
        """The clips' manifest: every animated attribute, declared with its type and no value."""
        Sdf = self._Sdf
        layer = Sdf.Layer.CreateAnonymous(".usda")
        for attribute, value_type in self._animated:
            prim = Sdf.CreatePrimInLayer(layer, attribute.GetPrimPath())
            Sdf.AttributeSpec(prim, attribute.name, value_type, Sdf.VariabilityVarying)
        return layer

    def _frame_layer(self, time_code: float, samples: list):
        """A layer holding one frame's samples, each (attribute path, value), at ``time_code``."""
        layer = self._Sdf.Layer.CreateAnonymous(self._format)
        self._add_samples(layer, time_code, samples)
        return layer

    def _add_samples(self, layer, time_code: float, samples: list) -> None:
        """Add samples, each (attribute path, value), at ``time_code`` to ``layer``."""
        Sdf = self._Sdf
        types = self._types
        for attribute, value in samples:
            if not layer.GetAttributeAtPath(attribute):
                prim = Sdf.CreatePrimInLayer(layer, attribute.GetPrimPath())
                Sdf.AttributeSpec(prim, attribute.name, types[attribute], Sdf.VariabilityVarying)
            layer.SetTimeSample(attribute, time_code, value)

    def _write_kept(self, kept: list, frames: int) -> None:
        """Write the frames of a stopped run being resumed, (attribute path, [(time code, value)]) pairs."""
        by_time: dict[float, list] = {}
        for attribute, values in kept:
            if attribute not in self._types:
                raise ConfigError(f"cannot resume {self.path!r}: it holds {attribute}, which this scene does not "
                                  "write (another scene or other export options)")
            for time_code, value in values:
                by_time.setdefault(time_code, []).append((attribute, value))
        for time_code in sorted(by_time):
            self._pending = (time_code, self._frame_layer(time_code, by_time[time_code]), None)
            self._save_layer()
            self._add_clip(*self._pending)
            self._gather()
        self._pending = None
        self.frame_count = frames

    def _pack(self) -> None:
        """Replace the root layer by one self-contained layer of every saved frame (the static layer with the
        frames' samples), written beside it and renamed over it, then remove the frames folder."""
        Sdf = self._Sdf
        packed = os.path.join(self.parts, PACKED_NAME + self._format)
        said: list = []
        try:
            with self._Tf.DiagnosticTrap() as trap:
                try:
                    self._pack_layer(packed)
                finally:
                    said = _trapped(trap)
            os.replace(packed, self.path)
        except (OSError, self._Tf.ErrorException) as exc:
            self._failed = True
            reason = _reason(exc, said) or _diagnose(self.path) or "USD gave no reason"
            code = getattr(exc, "errno", None)
            if code is None and _os_code(reason) is not None:
                code = _os_code(reason)
                reason = os_error_reason(OSError(code, os.strerror(code)))
            raise OutputError(f"cannot pack the USD file {self.path!r} into one file: {reason}; it holds frames "
                              f"0..{self.frames_saved - 1} through its frames folder {self.parts!r}",
                              path=self.path, frames_saved=self.frames_saved, code=code) from None
        self._reaper.packed()
        shutil.rmtree(self.parts, ignore_errors=True)
        layer = Sdf.Layer.Find(self.path)
        if layer is not None:  # a stale layer of this path in this process's registry: read the new file
            layer.Reload()

    def _pack_layer(self, packed: str) -> None:
        """Write the packed layer at ``packed``: the static layer with every clip's samples."""
        Sdf = self._Sdf
        static = os.path.join(self.parts, STATIC_NAME)
        layer = Sdf.Layer.Find(packed)  # a stale one of an earlier writer of this path, in this process
        if layer is not None:
            layer.Clear()
        else:
            layer = Sdf.Layer.CreateNew(packed)
        layer.TransferContent(Sdf.Layer.FindOrOpen(static))
        self._stage_metadata(layer, end=self._time_code(max(self.frames_saved - 1, 0)))
        if getattr(self, "_layer", None) is not None:
            self._layer.author_arc(layer)
        pending = 0  # bytes of samples (on disk, as clip files) gathered since the last save
        for clip in self._clips:
            clip_path = os.path.join(self.parts, clip.name)
            self._copy_samples(Sdf.Layer.OpenAsAnonymous(clip_path), layer)
            pending += os.path.getsize(clip_path)
            if not self._text and pending >= _PACK_FLUSH_BYTES:
                layer.Save()  # a crate appends: the samples saved leave memory
                pending = 0
        if self._clips:  # what the last frame lacks while frames come (its accelerations)
            self._add_samples(layer, self._clips[-1].last, self._closing_samples())
        if not layer.Save():
            raise OSError("USD did not save the packed file")
        del layer

    def _closing_samples(self) -> list:
        """Samples of the last frame that only the end of the run gives: none here (the writer's accelerations)."""
        return []

    @property
    def _text(self) -> bool:
        return self._format == ".usda"

    def _release(self) -> None:
        """Drop the stage (and the writer's prims), end the reaper (cleanly after a packed file, else it keeps the
        frames folder (the file's frames) and removes only temporaries), and let go of the output's lock if the
        writer took it."""
        self._closed = True
        self.stage = None
        self._slots = []
        self._pending = None
        reaper, self._reaper = getattr(self, "_reaper", None), None
        if reaper is not None:
            reaper.finish()
        lock, self._lock = getattr(self, "_lock", None), None
        if lock is not None and getattr(self, "_owns_lock", False):
            lock.release()

    def _abandon(self) -> None:
        """Undo a writer whose set-up failed: remove what it wrote."""
        self._release()
        shutil.rmtree(self.parts, ignore_errors=True)
        if os.path.isfile(self.path):
            os.remove(self.path)


#: Names inside the frames folder.
STATIC_NAME = "static.usdc"
MANIFEST_NAME = "manifest.usda"
PACKED_NAME = "packed"
#: Bytes of samples a packed crate file gathers between two saves (each save appends them to the file).
_PACK_FLUSH_BYTES = 256 << 20
#: Frames, or bytes of frames, gathered into one chunk layer while a run writes.
_CHUNK_FRAMES = 100
_CHUNK_BYTES = 64 << 20
#: Seconds a frame file a chunk replaced stays, for readers that opened the root before the chunk came.
_GRACE = 10.0


def parts_folder(path: str) -> str:
    """The folder beside ``path`` that holds its frames while a run writes them (``out.usdc.frames``)."""
    return path + ".frames"


def frame_name(time_code: float, fmt: str) -> str:
    """The file name of one frame's layer in the frames folder."""
    return f"frame.{int(time_code):06d}{fmt}"


def chunk_name(first: float, last: float, fmt: str) -> str:
    """The file name of a chunk of the frames of time codes ``first`` .. ``last`` in the frames folder."""
    return f"chunk.{int(first):06d}-{int(last):06d}{fmt}"


class _Clip(NamedTuple):
    """One clip layer of the stage while it is written: a frame (level -1) or a chunk of frames."""

    first: float  # time code of its first frame
    last: float  # time code of its last frame
    name: str  # file name in the frames folder
    level: int  # -1: one frame; 0: a chunk of loose frames; k + 1: two chunks of level k merged
    size: int  # bytes on disk


def _remove_output(path: str) -> None:
    """Remove an earlier output at ``path`` and its frames folder (a killed run's)."""
    from pxr import Sdf

    if os.path.exists(path):
        os.remove(path)
    shutil.rmtree(parts_folder(path), ignore_errors=True)
    layer = Sdf.Layer.Find(path)
    if layer is not None:  # a stale layer of the same name in this process's registry
        layer.Clear()


class _Reaper:
    """A small process that outlives a killed run: when the writer's process dies without finishing (even by
    SIGKILL, which no handler sees), it removes the temporary files USD was writing (USD writes a file as
    its name less the extension + "." + 6 characters, then renames it), so that a killed run leaves its file,
    its frames folder and nothing else. It notices the writer's death as the end of a pipe."""

    _CODE = r"""
import fcntl, os, re, shutil, sys, time
parts, path = sys.argv[1:3]
started = time.time() - 1.0
said = sys.stdin.read().split("\n")
if "done" not in said:
    for line in said:
        if line.startswith("obsolete "):
            try:
                os.remove(line[len("obsolete "):])
            except OSError:
                pass
    for name in os.listdir(parts) if os.path.isdir(parts) else []:
        if name.startswith("packed.") or not name.endswith((".usdc", ".usda")):  # USD's temporaries
            try:
                os.remove(os.path.join(parts, name))
            except OSError:
                pass
    folder, stem = os.path.split(os.path.splitext(path)[0])
    pattern = re.compile(re.escape(stem) + r"\.[A-Za-z0-9]{6}$")
    for name in os.listdir(folder):
        full = os.path.join(folder, name)
        try:
            if pattern.match(name) and os.path.getmtime(full) >= started:
                os.remove(full)
        except OSError:
            pass
    if "packed" in said:
        shutil.rmtree(parts, ignore_errors=True)
    lock = path + ".lock"  # the dead writer's lock, released by the kernel: removed unless another run took it
    for _ in range(100):
        try:
            handle = os.open(lock, os.O_RDWR | os.O_NOFOLLOW)
        except OSError:
            break
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(handle)
            time.sleep(0.02)  # its process is still closing its files, or another run holds it
            continue
        try:
            mine, there = os.fstat(handle), os.stat(lock, follow_symlinks=False)
            if (mine.st_dev, mine.st_ino) == (there.st_dev, there.st_ino):
                os.remove(lock)
        except OSError:
            pass
        os.close(handle)
        break
"""

    def __init__(self, path: str):
        self._process = subprocess.Popen(
            [sys.executable, "-c", self._CODE, parts_folder(path), os.path.abspath(path)], stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True, start_new_session=True, text=True,
        )

    def _tell(self, word: str) -> None:
        try:
            self._process.stdin.write(word + "\n")
            self._process.stdin.flush()
        except (OSError, ValueError):
            pass

    def obsolete(self, paths: list) -> None:
        """Frame files that a chunk replaced: removed by the writer after a grace period, or by the reaper."""
        for path in paths:
            self._tell(f"obsolete {path}")

    def packed(self) -> None:
        """The self-contained file replaced the root: the frames folder is no longer needed."""
        self._tell("packed")

    def finish(self) -> None:
        """The writer ended on its own: nothing to clean up."""
        self._tell("done")
        try:
            self._process.stdin.close()
        except OSError:
            pass
        self._process.wait()


def read_frames(path: str, frames: int, start_frame: int, *, step: float = 1.0) -> list:
    """Every time sample of the first ``frames`` frames (time codes ``start_frame`` + k × ``step``) of the USD file
    at ``path``, packed or a killed run's (read through its frames folder): (attribute path, [(time code, value)])
    pairs, read into memory so that the file can be replaced. Only the file's own layers are read (not a layer's
    asset beneath it)."""
    from pxr import Sdf, Tf, Usd

    if not os.path.isfile(path):
        raise ConfigError(f"cannot resume into {path!r}: the file is missing (resume writes into the stopped run's "
                          "output: pass the same -o)")
    said: list = []
    try:
        with Tf.DiagnosticTrap() as trap:  # USD's warnings (a clip it cannot open) go into the error, or nowhere
            try:
                layer = Sdf.Layer.FindOrOpen(path)
                if layer is not None:
                    layer.Reload()
                stage = Usd.Stage.Open(layer if layer is not None else path)
                own = (os.path.realpath(path), os.path.realpath(parts_folder(path)) + os.sep)
                for used in stage.GetUsedLayers():  # an asset beneath a layer over it: not the run's frames
                    real = os.path.realpath(used.realPath) if used.realPath else ""
                    if real and real != own[0] and not real.startswith(own[1]):
                        stage.MuteLayer(used.identifier)
                kept, last = [], -1.0
                end = start_frame + (frames - 0.5) * step  # frames 0 .. frames - 1
                for prim in stage.TraverseAll():
                    for attribute in prim.GetAttributes():
                        times = attribute.GetTimeSamples()
                        last = max([last, *times])
                        times = [t for t in times if start_frame <= t < end]
                        if times:
                            kept.append((attribute.GetPath(), [(t, attribute.Get(Usd.TimeCode(t))) for t in times]))
                del stage
            finally:
                said = _trapped(trap)
    except Tf.ErrorException as exc:
        raise ConfigError(f"cannot resume into {path!r}: USD cannot read it "
                          f"({_reason(exc, said) or 'no reason'})") from None
    held = int(round((last - start_frame) / step)) + 1
    if held < frames:
        raise ConfigError(f"cannot resume into {path!r}: it holds frames 0..{held - 1}, the checkpoint continues "
                          f"after frame {frames - 1}")
    return kept


def check_output_path(path: str | os.PathLike) -> str:
    """``path`` as a string if it can name a USD output file, else a ConfigError saying what is wrong.

    The extension picks the format (``.usdc`` or ``.usd``: binary crate; ``.usda``: text) and the folder
    must exist. Checked before a run builds its model, so a bad ``-o`` fails at once.
    """
    path = os.fspath(path)
    if os.path.splitext(path)[1].lower() not in _EXTENSIONS:
        raise ConfigError(f"USD output must end in .usdc (binary), .usda (text) or .usd (binary), got {path!r}")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ConfigError(f"output folder does not exist: {folder}")
    if os.path.isdir(path):
        raise ConfigError(f"USD output {path!r} is a folder, not a file")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"USD output {path!r} cannot be written: {os.strerror(errno.EACCES)} [EACCES] to "
                          f"create files in {folder}; check its permissions")
    if os.path.exists(path) and not os.access(path, os.W_OK):
        raise ConfigError(f"USD output {path!r} cannot be written: the file is read-only; check its permissions")
    problem = _probe_folder(folder)  # permissions do not tell all (a read-only or virtual file system, a quota)
    if problem:
        raise ConfigError(f"USD output {path!r} cannot be written: {problem}")
    return path


def _probe_folder(folder: str) -> str:
    """Why no file can be created in ``folder`` (the OS's reason), or "" when a probe file can be."""
    try:
        handle, probe = tempfile.mkstemp(prefix=".warpspring-", suffix=".probe", dir=folder)
    except OSError as exc:
        return f"cannot create a file in {folder}: {os_error_reason(exc)}"
    os.close(handle)
    try:
        os.remove(probe)
    except OSError:
        pass
    return ""


def _reason(error: BaseException, said: list | None = None) -> str:
    """The reason an OS or USD (Tf) error gives, on one line, with the messages USD posted meanwhile (``said``,
    from :func:`_trapped`); "" when it gives none. A Tf error's text is USD's call stack: only its messages (the
    quoted last part of each entry) are kept."""
    if isinstance(error, OSError) and (error.strerror or error.errno):
        return os_error_reason(error)
    entries = [str(a) for a in getattr(error, "args", ()) if str(a).strip()] or [str(error)]
    messages = list(said or ())
    for entry in entries:
        for line in entry.strip().splitlines():
            found = re.search(r" : '(.*)'\s*$", line.strip())
            message = " ".join((found.group(1) if found else line).split())
            if message and message not in messages:
                messages.append(message)
    return "; ".join(messages)


def _diagnose(path: str) -> str:
    """What the file system shows about writing ``path`` when a write failed without an OS reason: a full
    disk, a folder that is gone or refuses new files, a read-only file; "" when nothing is wrong there."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        return f"its folder {folder} does not exist"
    try:
        fs = os.statvfs(folder)
    except OSError:
        fs = None
    if fs is not None and fs.f_blocks > 0 and fs.f_bavail * fs.f_frsize < _LOW_SPACE:  # (virtual file systems: 0)
        return f"{fs.f_bavail * fs.f_frsize} bytes free in {folder}: {os.strerror(errno.ENOSPC)} {_FULL_DISK}"
    if os.path.exists(path) and not os.access(path, os.W_OK):
        return "the file is read-only"
    return _probe_folder(folder)


#: Free space [B] below which a failed write is put down to a full disk.
_LOW_SPACE = 1 << 20




def _trapped(trap) -> list[str]:
    """The messages of the warnings and errors USD posted in a ``Tf.DiagnosticTrap``, which are dismissed
    (they would otherwise be printed on stderr)."""
    said = []
    for diagnostic in [*trap.GetErrors(), *trap.GetWarnings()]:
        message = " ".join(str(diagnostic.commentary).split())
        if message and message not in said:
            said.append(message)
    trap.Clear()
    return said


#: The OS's words for the errors a write may end with, by error number.
_OS_MESSAGES = {code: os.strerror(code) for code in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.EFBIG)}
#: How :func:`_diagnose` ends when the disk is full.
_FULL_DISK = "[ENOSPC]"


def _os_code(text: str) -> int | None:
    """The error number whose words USD quoted in ``text`` (it reports OS errors in words only), or None."""
    for code, words in _OS_MESSAGES.items():
        if words in text:
            return code
    return None
