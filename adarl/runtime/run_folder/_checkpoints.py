"""A run folder's checkpoints: ``checkpoints/ckpt-<frames>.pt``, its replay buffer ``rb-<frames>/`` and ``best.pt``.

Part of :class:`adarl.runtime.run_folder.run_dir.RunDir` (a mixin: the folder's layout is described there). Each
checkpoint
is written to a temporary file, fsync'ed and renamed, so a crash or a full disk mid-write leaves the previous one
intact; each names the recipe fingerprint it was written under (:func:`recipe_fingerprint`), checked before any of
its tensors is used, and is loaded with ``weights_only=True`` (no code runs from the file).
"""

from __future__ import annotations

import errno
import os
import shutil
import warnings
from pathlib import Path

from adarl import __version__
from adarl.errors import (
    CheckpointError,
    CheckpointFallbackWarning,
    command,
    describe_os_error,
)
from adarl.runtime.families import family
from adarl.runtime.run_folder._file_safety import (
    NotAFile,
    UnsafeFile,
    atomic_torch_save,
    buffer_nbytes,
    check_dumps_folder,
    check_free_space,
    fsync_dir,
    nbytes,
    safe_load,
    why_unloadable,
)

CHECKPOINT_FORMAT = "adarl.checkpoint"
CHECKPOINT_VERSION = 1
REPLAY_BUFFER_FILE = "buffer.pt"  # inside rb-<frames>/; older checkpoints hold TorchRL's dumps() layout there


def recipe_fingerprint(recipe) -> dict:
    """What fixes the shapes of a run's checkpoints: env, algorithm, network layout, critics, buffer size.

    A checkpoint written under another value cannot be loaded into this run's networks and buffer; it is refused
    by name before any tensor is used (keys absent on either side, from other adarl versions, are not compared)."""
    fp = {
        "algorithm.name": recipe.algorithm.name,
        "algorithm.options": dict(recipe.algorithm.options),
        "env.id": recipe.env.id,
        "env.num_envs": recipe.env.num_envs,
        "env.normalize_observations": recipe.env.normalize_observations,  # what the buffer and networks were fed
        "algorithm.num_qvalue_nets": recipe.algorithm.num_qvalue_nets,
        "algorithm.fixed_alpha": recipe.algorithm.fixed_alpha,
        "algorithm.parseval.diagonal": recipe.algorithm.parseval.diagonal,
        "algorithm.parseval.input_scale": recipe.algorithm.parseval.input_scale,
        "replay.size": recipe.replay.size,
    }
    for net in ("actor", "critic"):
        m = getattr(recipe.network, net)
        fp[f"network.{net}.num_cells"] = list(m.num_cells)
        fp[f"network.{net}.low_rank_layers"] = list(m.low_rank_layers)
        fp[f"network.{net}.rank"] = m.rank
        fp[f"network.{net}.sparse"] = m.sparse.model_dump()
    for key in family(recipe).fingerprint:  # the loop's own shape-fixing keys (PPO's observation norm and policy)
        fp[key] = _dotted(recipe, key)
    return fp


def _dotted(recipe, key: str):
    """The recipe's value at a dotted key (``algorithm.ppo.policy``)."""
    value = recipe
    for part in key.split("."):
        value = getattr(value, part)
    return value


def _same_in_fingerprint(key: str, theirs: dict, ours: dict) -> bool:
    """Whether a checkpoint's fingerprint entry matches this run's. Checkpoints written before RNAC became the
    registered algorithms ``rnac_ipm``/``rnac_ds`` say ``ppo`` and have no options (their recipe.yaml's old
    ``algorithm.rnac`` section is read as the new name, :mod:`adarl.runtime.config.schema`)."""
    if theirs[key] == ours[key]:
        return True
    return (
        key == "algorithm.name"
        and theirs[key] == "ppo"
        and str(ours[key]).startswith("rnac_")
        and "algorithm.options" not in theirs
    )


class RunCheckpoints:
    """The checkpoints :class:`~adarl.runtime.run_folder.run_dir.RunDir` writes and reads below ``self.path``."""

    path: Path
    _buffer_cache: tuple[Path, dict] | None

    def ensure_present(self) -> None:  # pragma: no cover - RunDir's
        raise NotImplementedError

    @property
    def checkpoint_dir(self) -> Path:
        return self.path / "checkpoints"

    # ------------------------------------------------------------------ checkpoints
    def checkpoints(self) -> list[Path]:
        """Checkpoint files, oldest first."""
        d = self.checkpoint_dir
        return sorted(d.glob("ckpt-*.pt")) if d.is_dir() else []

    def latest_checkpoint_frames(self) -> int | None:
        """The frames of the newest checkpoint (what ``adarl resume`` starts from, if it loads), None without one."""
        return max((f for f in map(_frames_of, self.checkpoints()) if f is not None), default=None)

    @property
    def best_checkpoint_path(self) -> Path:
        """``checkpoints/best.pt``: the state at the best nominal evaluation so far (no replay buffer)."""
        return self.checkpoint_dir / "best.pt"

    def _payload(self, state: dict, frames: int, fingerprint: dict | None, **extra) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "adarl_version": __version__,
            "frames": int(frames),
            "recipe_fingerprint": fingerprint,
            **extra,
            "state": state,
        }

    def save_checkpoint(
        self, state: dict, *, frames: int, keep_last: int = 3, replay_buffer=None, fingerprint: dict | None = None
    ) -> Path:
        """Write ``ckpt-<frames>.pt`` (and the replay buffer beside it) atomically, then delete the oldest.

        Order: buffer to a temporary folder, renamed; checkpoint to a temporary file, fsync'ed, renamed; folder
        fsync'ed; only then older checkpoints are removed. A crash or a full disk at any point leaves the previous
        checkpoint loadable; on a write error the partial files are removed and :class:`CheckpointError` says so.
        The buffer is written with ordinary writes (a full disk is an ``OSError``), never memory-mapped: TorchRL's
        ``dumps()`` memory-maps its files, and a full disk then kills the process with SIGBUS, with no message.
        ``fingerprint``: :func:`recipe_fingerprint` of the run, checked when the checkpoint is loaded.
        """
        self.ensure_present()
        path = self.checkpoint_dir / f"ckpt-{int(frames):012d}.pt"
        rb_dir = self.checkpoint_dir / f"rb-{int(frames):012d}"
        rb_tmp = rb_dir.with_name(rb_dir.name + ".tmp")
        rb_old = _set_aside(rb_dir)
        writing = self.checkpoint_dir  # what the message names when a write fails
        try:
            self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
            if replay_buffer is not None:
                shutil.rmtree(rb_tmp, ignore_errors=True)
                writing = rb_dir / REPLAY_BUFFER_FILE
                check_free_space(
                    self.checkpoint_dir,
                    buffer_nbytes(replay_buffer) + nbytes(state),
                    "the checkpoint with its replay buffer",
                )
                rb_tmp.mkdir()
                atomic_torch_save(replay_buffer.state_dict(), rb_tmp / REPLAY_BUFFER_FILE)
                if rb_dir.exists():
                    # Written again at the same frames (the run's end): the old buffer is renamed aside, not emptied
                    # in place, so that a kill meanwhile never leaves the checkpoint beside a half-deleted buffer.
                    # Until the new checkpoint file replaces the old one, the set-aside folder is the old file's
                    # buffer: a kill between the two renames leaves it where loading looks (_buffer_dir_on_disk).
                    shutil.rmtree(rb_old, ignore_errors=True)
                    os.replace(rb_dir, rb_old)
                os.replace(rb_tmp, rb_dir)
            writing = path
            atomic_torch_save(self._payload(state, frames, fingerprint, replay_buffer=replay_buffer is not None), path)
            fsync_dir(self.checkpoint_dir)
            shutil.rmtree(rb_old, ignore_errors=True)
        except OSError as err:
            shutil.rmtree(rb_tmp, ignore_errors=True)
            if replay_buffer is not None and not path.exists():
                shutil.rmtree(rb_dir, ignore_errors=True)
            prev = [p.name for p in self.checkpoints() if p != path]
            full = err.errno in (errno.ENOSPC, errno.EDQUOT)
            remedy = "free space" if full else f"make {str(self.path)!r} writable"
            raise CheckpointError(
                f"could not write checkpoint {path.name}{' (disk full)' if full else ''}: {str(writing)!r}: "
                f"{err.strerror or err}; the run stopped. The previous checkpoint {prev[-1] if prev else '(none)'} "
                f"is intact: {remedy} and `{command('adarl', 'resume', self.path)}`",
                path=path,
                reason=err.strerror or str(err),
            ) from None
        for old in self.checkpoints()[:-keep_last]:
            old.unlink(missing_ok=True)
            shutil.rmtree(self._replay_buffer_dir(old), ignore_errors=True)
            shutil.rmtree(_set_aside(self._replay_buffer_dir(old)), ignore_errors=True)
        return path

    def save_best(self, state: dict, *, frames: int, score: float, fingerprint: dict | None = None) -> Path | None:
        """Replace ``checkpoints/best.pt`` (atomically); a write error keeps the old one and only warns."""
        self.ensure_present()
        try:
            self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
            atomic_torch_save(self._payload(state, frames, fingerprint, score=float(score)), self.best_checkpoint_path)
        except OSError as err:
            warnings.warn(f"could not update {self.best_checkpoint_path}: {describe_os_error(err)}", stacklevel=2)
            return None
        return self.best_checkpoint_path

    @staticmethod
    def _replay_buffer_dir(checkpoint: Path, frames: int | None = None) -> Path:
        """``rb-<frames>/`` beside the checkpoint file (wherever that file is)."""
        if frames is None:
            frames = int(checkpoint.name.split(".")[0].removeprefix("ckpt-"))
        return checkpoint.parent / f"rb-{int(frames):012d}"

    def load_checkpoint(
        self, path: str | os.PathLike, *, fingerprint: dict | None = None, replay_buffer: bool = True
    ) -> dict:
        """Load one checkpoint safely (``weights_only=True``: no code runs from the file) and check it fits.

        ``fingerprint`` (:func:`recipe_fingerprint` of the run): a checkpoint written under another recipe is refused
        before any tensor is used. ``replay_buffer``: require the buffer it was saved with, beside the file, and read
        it (a damaged buffer refuses the checkpoint; evaluation and policies do not need it). Only regular files are
        read (a FIFO would block). The state gets ``checkpoint_file``, where the buffer is looked for."""
        path = Path(path)

        def refuse(reason: str) -> CheckpointError:
            return CheckpointError(f"checkpoint {str(path)!r} {reason}", path=path, reason=reason)

        try:
            payload = safe_load(path)
        except FileNotFoundError:
            raise refuse("does not exist") from None
        except NotAFile as err:
            raise refuse(str(err)) from None
        except Exception as err:  # truncated zip, pickle with code, garbage bytes
            raise refuse(f"cannot be loaded safely: {why_unloadable(err)}") from None
        if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
            raise refuse("is not an adarl checkpoint (format marker missing)")
        state = payload.get("state")
        try:  # the fields everything below relies on, of the right kinds (a file may hold anything plain)
            version = int(payload.get("version", 0))
            if version > CHECKPOINT_VERSION:  # a newer layout: say so before judging it by this one
                raise refuse(
                    f"was written by a newer adarl (checkpoint version {version}, this version reads up to "
                    f"{CHECKPOINT_VERSION}); upgrade adarl to load it"
                )
            frames = int(payload.get("frames", state["counters"]["frames"]))
            int(state["counters"]["frames"])
        except (TypeError, ValueError, KeyError, IndexError):
            raise refuse("is not an adarl checkpoint (no training state in it)") from None
        theirs = payload.get("recipe_fingerprint")
        if fingerprint is not None and isinstance(theirs, dict):
            differ = [k for k in fingerprint if k in theirs and not _same_in_fingerprint(k, theirs, fingerprint)]
            if differ:
                shown = "; ".join(f"{k}: {theirs[k]} in it, {fingerprint[k]} in this run" for k in differ[:3])
                raise refuse(
                    f"was written for another recipe ({shown}{'; ...' if len(differ) > 3 else ''}); it "
                    f"cannot be loaded into this run's networks"
                )
        if replay_buffer and payload.get("replay_buffer"):
            rb = _buffer_dir_on_disk(self._replay_buffer_dir(path, frames))
            if not rb.is_dir():
                raise refuse(f"has lost its replay buffer: the folder {rb.name} is missing beside it")
            buffer_file = rb / REPLAY_BUFFER_FILE
            if not (buffer_file.exists() or buffer_file.is_symlink() or (rb / "storage").is_dir()):
                # (neither this version's buffer.pt nor an older one's dumps() folder: emptied by a kill mid-write)
                raise refuse(f"has lost its replay buffer: {rb.name} holds no {REPLAY_BUFFER_FILE}")
            if buffer_file.exists() or buffer_file.is_symlink():
                # Read now, not when the trainer fills its buffer: a damaged buffer makes the whole checkpoint
                # unusable, so resume falls back to the previous one as for a missing buffer (kept for
                # load_replay_buffer, which then does not read the file again).
                self._buffer_cache = None
                try:
                    self._buffer_cache = (rb.absolute(), safe_load(buffer_file))
                except NotAFile as err:
                    raise refuse(f"has lost its replay buffer: {rb.name}/{REPLAY_BUFFER_FILE} {err}") from None
                except Exception as err:  # noqa: BLE001 - any unreadable buffer file is refused the same way
                    raise refuse(
                        f"has lost its replay buffer: {rb.name}/{REPLAY_BUFFER_FILE} cannot be loaded safely: "
                        f"{why_unloadable(err)}"
                    ) from None
            else:  # an older checkpoint's TorchRL dumps() folder: read by pickle and imports, so checked first
                try:
                    check_dumps_folder(rb)
                except (UnsafeFile, OSError) as err:
                    raise refuse(f"has lost its replay buffer: {rb.name}/{err}") from None
        state["checkpoint_file"] = str(path)
        return state

    def load_latest_checkpoint(
        self,
        *,
        quarantine: bool = False,
        fingerprint: dict | None = None,
        strict: bool = False,
        replay_buffer: bool = True,
    ) -> dict:
        """The newest checkpoint that loads. A newer one that does not (damaged, or for another recipe) is skipped
        with a :class:`~adarl.errors.CheckpointFallbackWarning` naming it and why, never silently.

        ``strict=True`` (``--checkpoint latest``): the newest or a :class:`CheckpointError`, no fallback.
        ``quarantine=True`` (resume) renames skipped ones to ``*.pt.corrupt`` (so rotation never keeps them in place
        of good checkpoints) and deletes their replay-buffer folders (useless without them, and large).
        """
        errors, bad = [], []
        for path in reversed(self.checkpoints()):
            try:
                state = self.load_checkpoint(path, fingerprint=fingerprint, replay_buffer=replay_buffer)
            except CheckpointError as err:
                if strict:
                    raise CheckpointError(
                        f"{err}; --checkpoint latest does not fall back to an older checkpoint "
                        f"(without it, the newest one that loads is used)",
                        path=err.path,
                        reason=err.reason,
                    ) from None
                errors.append(str(err))
                bad.append((path, err.reason))
                continue
            frames = int(state["counters"]["frames"])
            for b, reason in bad:
                note = ""
                if quarantine:
                    os.replace(b, b.with_name(b.name + ".corrupt"))
                    shutil.rmtree(self._replay_buffer_dir(b), ignore_errors=True)
                    note = f" (renamed {b.name}.corrupt)"
                lost = _frames_of(b) - frames if _frames_of(b) is not None else None
                warnings.warn(
                    f"skipped checkpoint {b.name}{note}: {reason}; using {path.name} instead"
                    + (f", {lost} frames earlier" if lost is not None and lost > 0 else "")
                    + " (--checkpoint latest refuses instead)",
                    CheckpointFallbackWarning,
                    stacklevel=2,
                )
            return state
        if errors:
            raise CheckpointError(
                "no loadable checkpoint in run folder: " + "; ".join(errors) + "; `adarl run RECIPE -o "
                f"{command(self.path)} --overwrite` trains it again from the start"
            )
        raise CheckpointError(
            f"no checkpoint in {str(self.checkpoint_dir)!r} to resume from, though the run folder holds training "
            f"records (were its checkpoints deleted?); `adarl run RECIPE -o {command(self.path)} --overwrite` trains "
            f"it again from the start"
        )

    def load_replay_buffer(self, replay_buffer, *, frames: int, checkpoint: str | os.PathLike | None = None) -> bool:
        """Fill ``replay_buffer`` from ``rb-<frames>/`` beside ``checkpoint`` (default: in this run's checkpoints);
        False when there is none. Reads this version's ``buffer.pt`` or an older checkpoint's ``dumps()`` folder."""
        base = Path(checkpoint).parent if checkpoint is not None else self.checkpoint_dir
        rb_dir = _buffer_dir_on_disk(base / f"rb-{int(frames):012d}")
        if not rb_dir.is_dir():
            return False
        cached, self._buffer_cache = self._buffer_cache, None
        if cached is not None and cached[0] == rb_dir.absolute():  # read (and checked) by load_checkpoint
            replay_buffer.load_state_dict(cached[1])
        elif (rb_dir / REPLAY_BUFFER_FILE).exists() or (rb_dir / REPLAY_BUFFER_FILE).is_symlink():
            try:
                sd = safe_load(rb_dir / REPLAY_BUFFER_FILE)
            except Exception as err:  # noqa: BLE001 - any unreadable file is refused the same way
                raise CheckpointError(
                    f"replay buffer {str(rb_dir / REPLAY_BUFFER_FILE)!r} cannot be loaded safely: "
                    f"{why_unloadable(err)}",
                    path=rb_dir,
                    reason=why_unloadable(err),
                ) from None
            replay_buffer.load_state_dict(sd)
        else:  # an older checkpoint's TorchRL dumps() folder: only raw tensors and JSON are read from it
            try:
                check_dumps_folder(rb_dir)
            except (UnsafeFile, OSError) as err:
                raise CheckpointError(
                    f"replay buffer {str(rb_dir)!r} cannot be loaded safely: {err}", path=rb_dir, reason=str(err)
                ) from None
            replay_buffer.loads(str(rb_dir))
        return True


def _set_aside(rb_dir: Path) -> Path:
    """Where :meth:`RunCheckpoints.save_checkpoint` moves ``rb-<frames>/`` while it writes the same frames again."""
    return rb_dir.with_name(rb_dir.name + ".old.tmp")


def _buffer_dir_on_disk(rb_dir: Path) -> Path:
    """``rb-<frames>/``, or its set-aside copy when a kill fell between a rewrite's two renames (the old buffer
    renamed aside, the new one not yet in place). The checkpoint file is then still the old one, and the set-aside
    buffer is the one it was written with: loading it resumes from that checkpoint instead of one further back."""
    if not rb_dir.is_dir() and _set_aside(rb_dir).is_dir():
        return _set_aside(rb_dir)
    return rb_dir


def _frames_of(checkpoint: Path) -> int | None:
    try:
        return int(checkpoint.name.split(".")[0].removeprefix("ckpt-"))
    except ValueError:
        return None
