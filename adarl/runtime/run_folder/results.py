"""Results at an fsspec URL (``s3://bucket/exp``, ``gs://...``, ``file:///shared/exp``): every run trains in a local
scratch folder and is copied to ``<URL>/<run id>/``; everything else reads and writes the URL through fsspec.

Why a scratch folder: a run's checkpoints are made safe by fsync + atomic rename
(:mod:`adarl.runtime.run_folder.run_dir`), and
object stores have neither rename (a "move" is a copy then a delete) nor append. So the run writes exactly as on a local
disk, and :class:`RunMirror` copies its folder to the URL, in an order that keeps the URL consistent for a reader:

- after each new checkpoint, while the run goes on (and every ``SYNC_INTERVAL_S`` for the metrics): the metric
  files (complete lines only), the checkpoint's replay buffer, the checkpoint itself as ``*.part-*`` then moved into
  place, then ``checkpoints/LATEST`` (``{"checkpoint", "frames", "replay_buffer"}``) written last, then the older
  checkpoints at the URL deleted. A reader trusts only ``LATEST``, which names a checkpoint complete with its buffer;
- at the end: everything, ``summary.json`` last, so a run that looks finished at the URL has all its files there.

A retried run, on any machine, whose scratch folder lacks the URL's latest checkpoint downloads the run folder
(``LATEST``'s checkpoint only) and resumes from it. Why fsspec: it is the file-system layer of pandas, dask and torch
(installed with torch); S3 (``s3fs``), Google Cloud Storage (``gcsfs``), Azure (``adlfs``), SFTP, HDFS... plug into
it as packages, with no code here.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import socket
import tempfile
import time
import uuid
from pathlib import Path

import fsspec
from fsspec.registry import known_implementations

from adarl.errors import AdaRLError, AdaRLValueError

__all__ = [
    "is_url",
    "filesystem",
    "join",
    "read_text",
    "exists",
    "write_atomic",
    "makedirs",
    "RunMirror",
    "scratch_folder",
    "download_results",
    "upload_tree",
    "LATEST",
    "SYNC_INTERVAL_S",
]

LATEST = "LATEST"  # checkpoints/LATEST at the URL: the one checkpoint a reader may use
SYNC_INTERVAL_S = 30.0  # metrics go up at least this often while a run trains (and after every checkpoint)
_PART = ".part-"  # temporary names at the URL, moved into place when complete
_COMMON = "s3, gs, az, abfs, hf, sftp, hdfs, file"


def is_url(path) -> bool:
    """A string with a protocol (``s3://...``, ``file:///...``); plain paths and ``Path`` objects are not URLs."""
    return isinstance(path, str) and "://" in path


def _backend_package(protocol: str, err: Exception) -> str:
    """What to pip install for ``protocol``: the backend's own package (s3fs, gcsfs, adlfs...), or for fsspec's
    built-in filesystems the packages its message names (paramiko for sftp, aiohttp for http...)."""
    top = known_implementations.get(protocol, {}).get("class", "").split(".")[0]
    if top and top != "fsspec":
        return top
    quoted = re.findall(r'"([A-Za-z0-9_.\-]+)"', str(err))
    return " ".join(quoted) or {"hdfs": "pyarrow", "arrow_hdfs": "pyarrow"}.get(protocol, protocol)


def filesystem(url: str):
    """``(fs, path)`` for ``url`` (:func:`fsspec.core.url_to_fs`); a clear error for an unknown protocol or a
    protocol whose package is not installed (the message names what to ``pip install``)."""
    protocol = url.split("://", 1)[0]
    try:
        return fsspec.core.url_to_fs(url)
    except ImportError as err:
        raise AdaRLValueError(
            f"results URL {url!r}: the {protocol}:// filesystem needs a package that is not installed: "
            f"pip install {_backend_package(protocol, err)} (fsspec says: {err})"
        ) from None
    except ValueError as err:
        if "protocol" not in str(err).lower():
            raise
        raise AdaRLValueError(
            f"results URL {url!r}: unknown protocol {protocol!r}; fsspec knows e.g. {_COMMON} (all: "
            f"fsspec.available_protocols()); a plain path needs no protocol"
        ) from None


def join(base: str, *parts: str) -> str:
    """``base/part/...`` for a URL (``/`` separators whatever the OS)."""
    return "/".join([str(base).rstrip("/"), *(p.strip("/") for p in parts)])


def read_text(url: str) -> str | None:
    """The text of the file at ``url``, or None when there is none."""
    fs, path = filesystem(url)
    try:
        return fs.cat_file(path).decode()
    except (FileNotFoundError, IsADirectoryError):
        return None


def exists(url: str) -> bool:
    fs, path = filesystem(url)
    return fs.exists(path)


def makedirs(url: str) -> None:
    fs, path = filesystem(url)
    fs.makedirs(path, exist_ok=True)


def _mkparent(fs, path: str) -> None:
    fs.makedirs(fs._parent(path), exist_ok=True)  # a no-op on object stores; local-like filesystems need it


def _put_bytes(fs, path: str, data: bytes, *, atomic: bool) -> None:
    _mkparent(fs, path)
    if not atomic:
        fs.pipe_file(path, data)
        return
    tmp = f"{path}{_PART}{uuid.uuid4().hex[:8]}"
    fs.pipe_file(tmp, data)
    fs.mv(tmp, path)


def _put_file(fs, local: Path, path: str, *, atomic: bool) -> None:
    _mkparent(fs, path)
    if not atomic:
        fs.put_file(str(local), path)
        return
    tmp = f"{path}{_PART}{uuid.uuid4().hex[:8]}"
    fs.put_file(str(local), tmp)
    fs.mv(tmp, path)


def _put_many(fs, local: list[Path], paths: list[str]) -> None:
    """Upload files in one call (concurrent on async filesystems such as s3fs)."""
    for parent in sorted({fs._parent(p) for p in paths}):
        fs.makedirs(parent, exist_ok=True)
    if paths:
        fs.put([str(f) for f in local], paths)


def _get_many(fs, paths: list[str], local: list[Path]) -> None:
    """Download files in one call (concurrent on async filesystems such as s3fs)."""
    for parent in sorted({f.parent for f in local}):
        parent.mkdir(parents=True, exist_ok=True)
    if paths:
        fs.get(paths, [str(f) for f in local])


def write_atomic(url: str, data: str | bytes) -> None:
    """Write ``data`` to ``url`` under a temporary name, then move it into place: a reader sees the old or the new."""
    fs, path = filesystem(url)
    _put_bytes(fs, path, data.encode() if isinstance(data, str) else data, atomic=True)


def _is_temp(rel: str) -> bool:
    """Files never copied between a scratch folder and the URL: temporary names, and the run folder's lock (which
    process trains in a folder is a fact of one machine; a lock file is made wherever the run resumes)."""
    name = rel.rsplit("/", 1)[-1]
    return _PART in name or name.endswith(".tmp") or name == ".adarl.lock"


def _files(fs, root: str) -> list[str]:
    """Paths of every file under ``root``, relative to it (``/``-separated)."""
    root = root.rstrip("/")
    try:
        found = fs.find(root, withdirs=False)
    except FileNotFoundError:
        return []
    return sorted(p[len(root) :].lstrip("/") for p in found if p.rstrip("/") != root)


def scratch_folder(run_path: str, run_id: str, scratch: str | None) -> Path:
    """The local folder a URL run trains in: ``<scratch>/<hash of the experiment URL>/<run id>``.

    ``scratch`` defaults to ``$TMPDIR/adarl-scratch`` of the machine the run lands on (node-local disk on most
    clusters); the hash keeps two experiments' runs of the same name apart."""
    base = Path(os.path.expanduser(scratch)) if scratch else Path(tempfile.gettempdir()) / "adarl-scratch"
    parent = run_path.rstrip("/").rsplit("/", 1)[0]
    return base / hashlib.sha1(parent.encode()).hexdigest()[:12] / run_id


def _checkpoint_frames(name: str) -> int | None:
    try:
        return int(name.removeprefix("ckpt-").removesuffix(".pt"))
    except ValueError:
        return None


class RunMirror:
    """A run's local scratch folder and its folder at a URL (see the module docstring for the protocol).

    Beside the scratch folder: ``<run id>.synced.json`` (what was uploaded: size and mtime per file, and the frames
    of the URL's latest checkpoint), ``<run id>.upload/`` (hard links freezing the checkpoint being uploaded, so
    that the run may rotate it away meanwhile) and ``<run id>.download/`` (a download until it is complete)."""

    def __init__(self, local: str | os.PathLike, url: str) -> None:
        self.local, self.url = Path(local), url.rstrip("/")
        self.fs, self.root = filesystem(self.url)
        self.root = self.root.rstrip("/")
        self._manifest_path = self.local.with_name(self.local.name + ".synced.json")
        self._snapshot = self.local.with_name(self.local.name + ".upload")
        try:
            self.synced: dict = json.loads(self._manifest_path.read_text())
        except (OSError, ValueError):
            self.synced = {}
        self.last_push = time.monotonic()

    def _remote(self, rel: str) -> str:
        return f"{self.root}/{rel}"

    # ------------------------------------------------------------------ state
    def remote_latest(self) -> dict | None:
        """The URL's ``checkpoints/LATEST`` pointer, or None when no checkpoint was uploaded (completely) yet."""
        try:
            info = json.loads(self.fs.cat_file(self._remote(f"checkpoints/{LATEST}")))
            int(info["frames"]), str(info["checkpoint"])
        except (FileNotFoundError, ValueError, KeyError, TypeError):
            return None
        return info

    def local_checkpoints(self) -> list[tuple[int, Path]]:
        """``(frames, path)`` of the scratch folder's checkpoints, oldest first."""
        d = self.local / "checkpoints"
        found = [(_checkpoint_frames(p.name), p) for p in d.glob("ckpt-*.pt")] if d.is_dir() else []
        return sorted((f, p) for f, p in found if f is not None)

    def prepare(self) -> str:
        """Make the scratch folder hold the run's latest state before an attempt.

        ``"resume"``: a checkpoint is in the scratch folder (downloaded first when the URL's is newer or the scratch
        folder has none). ``"fresh"``: the URL has no checkpoint, so both folders are emptied, as a local start that
        never checkpointed is."""
        latest = self.remote_latest()
        self.synced = {}
        self._manifest_path.unlink(missing_ok=True)
        if latest is None:
            shutil.rmtree(self.local, ignore_errors=True)
            if self.fs.exists(self.root):
                self.fs.rm(self.root, recursive=True)
            return "fresh"
        local = self.local_checkpoints()
        if not local or local[-1][0] < int(latest["frames"]):
            shutil.rmtree(self.local, ignore_errors=True)
            self.download(latest)
        return "resume"

    def download(self, latest: dict) -> None:
        """Copy the run folder from the URL: every file but the checkpoints other than ``latest``'s (and best.pt).

        Into a temporary folder renamed into place at the end, so that a download cut short leaves no checkpoint
        without its replay buffer in the scratch folder."""
        frames = int(latest["frames"])
        keep = {f"checkpoints/{latest['checkpoint']}", "checkpoints/best.pt"}
        rb = f"checkpoints/rb-{frames:012d}/"
        rels = [
            rel
            for rel in _files(self.fs, self.root)
            if not _is_temp(rel) and (not rel.startswith("checkpoints/") or rel in keep or rel.startswith(rb))
        ]
        tmp = self.local.with_name(self.local.name + ".download")
        shutil.rmtree(tmp, ignore_errors=True)
        _get_many(self.fs, [self._remote(rel) for rel in rels], [tmp / rel for rel in rels])
        shutil.rmtree(self.local, ignore_errors=True)
        tmp.mkdir(parents=True, exist_ok=True)
        tmp.rename(self.local)
        for rel in rels:
            st = (self.local / rel).stat()
            self.synced[rel] = [st.st_size, st.st_mtime_ns]
        self.synced["@latest"] = frames
        self._save()

    def has_new_checkpoint(self) -> bool:
        ckpts = self.local_checkpoints()
        return bool(ckpts) and ckpts[-1][0] != self.synced.get("@latest")

    # ------------------------------------------------------------------ upload
    def push(self, *, final: bool = False) -> None:
        """Upload what changed since the last push; ``final`` (the run has ended) adds ``summary.json``, last."""
        if not self.local.is_dir():
            return
        ckpts = self.local_checkpoints()  # listed before the metrics are read: those then hold every row <= it
        for path in sorted(self.local.rglob("*")):
            rel = path.relative_to(self.local).as_posix()
            if path.is_file() and not rel.startswith("checkpoints/") and rel != "summary.json" and not _is_temp(rel):
                self._push_file(path, rel)
        if ckpts and ckpts[-1][0] != self.synced.get("@latest"):
            self._push_checkpoint(*ckpts[-1])
        best = self.local / "checkpoints" / "best.pt"
        if best.is_file():
            self._push_file(best, "checkpoints/best.pt", atomic=True)
        if final and (self.local / "summary.json").is_file():
            self._push_file(self.local / "summary.json", "summary.json", atomic=True)
        self._save()
        self.last_push = time.monotonic()

    def _push_file(self, path: Path, rel: str, *, atomic: bool = False) -> None:
        try:
            st = path.stat()
            data = path.read_bytes()  # one read: a file replaced atomically meanwhile is seen whole, old or new
        except FileNotFoundError:
            return
        key = [st.st_size, st.st_mtime_ns]
        if self.synced.get(rel) == key:
            return
        if rel.endswith(".csv") and not data.endswith(b"\n"):  # a row being appended goes up next time, whole
            data, key = data[: data.rfind(b"\n") + 1], None
        _put_bytes(self.fs, self._remote(rel), data, atomic=atomic)
        self.synced[rel] = key

    def _push_checkpoint(self, frames: int, ckpt: Path) -> None:
        snap = self._snapshot
        shutil.rmtree(snap, ignore_errors=True)
        rb = ckpt.with_name(f"rb-{frames:012d}")
        try:
            snap.mkdir(parents=True)
            _link(ckpt, snap / ckpt.name)
            rb_files = [f for f in sorted(rb.rglob("*")) if f.is_file()] if rb.is_dir() else []
            for f in rb_files:
                _link(f, snap / "rb" / f.relative_to(rb))
            if not ckpt.exists():  # rotated away meanwhile (its buffer maybe partly gone): take a newer one later
                raise FileNotFoundError(ckpt)
        except FileNotFoundError:
            shutil.rmtree(snap, ignore_errors=True)
            return
        rels = [f.relative_to(rb) for f in rb_files]
        _put_many(
            self.fs,
            [snap / "rb" / r for r in rels],
            [self._remote(f"checkpoints/rb-{frames:012d}/{r.as_posix()}") for r in rels],
        )
        _put_file(self.fs, snap / ckpt.name, self._remote(f"checkpoints/{ckpt.name}"), atomic=True)
        pointer = {
            "checkpoint": ckpt.name,
            "frames": frames,
            "replay_buffer": bool(rb_files),
            "time": time.time(),
            "host": socket.gethostname(),
        }
        _put_bytes(self.fs, self._remote(f"checkpoints/{LATEST}"), json.dumps(pointer).encode(), atomic=True)
        self.synced["@latest"] = frames
        keep = {ckpt.name, f"rb-{frames:012d}", "best.pt", LATEST}
        for p in self.fs.ls(self._remote("checkpoints"), detail=False):
            if p.rstrip("/").rsplit("/", 1)[-1] not in keep:
                self.fs.rm(p, recursive=True)
        shutil.rmtree(snap, ignore_errors=True)

    def _save(self) -> None:
        self._manifest_path.parent.mkdir(parents=True, exist_ok=True)
        self._manifest_path.write_text(json.dumps(self.synced))

    def clean(self) -> None:
        """Remove the scratch folder and its bookkeeping (after the run is finished at the URL)."""
        shutil.rmtree(self.local, ignore_errors=True)
        shutil.rmtree(self._snapshot, ignore_errors=True)
        shutil.rmtree(self.local.with_name(self.local.name + ".download"), ignore_errors=True)
        self._manifest_path.unlink(missing_ok=True)


def _link(src: Path, dest: Path) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dest)
    except FileNotFoundError:
        raise
    except OSError:  # no hard links on this filesystem: a copy freezes it too
        shutil.copy2(src, dest)


def download_results(url: str, dest: str | os.PathLike, *, checkpoints: bool = False) -> Path:
    """Copy the results at ``url`` (an experiment folder, a run folder or a folder of runs) into ``dest``: what a
    report reads, i.e. everything but checkpoints (unless ``checkpoints``), attempts, logs and earlier reports."""
    fs, root = filesystem(url)
    root = root.rstrip("/")
    if not fs.isdir(root):
        raise AdaRLError(f"{url!r} is not a folder (expected a run folder, an experiment folder, or a folder of runs)")
    dest = Path(dest)
    rels = []
    for rel in _files(fs, root):
        parts = rel.split("/")
        if not (
            _is_temp(rel)
            or rel.endswith(".log")
            or parts[0] in ("attempts", "report", "submitit")
            or (not checkpoints and "checkpoints" in parts[:-1])
        ):
            rels.append(rel)
    _get_many(fs, [f"{root}/{rel}" for rel in rels], [dest / rel for rel in rels])
    dest.mkdir(parents=True, exist_ok=True)
    return dest


def upload_tree(local: str | os.PathLike, url: str) -> None:
    """Copy every file under the local folder ``local`` to ``url`` (a report, sweep results: read when complete)."""
    fs, root = filesystem(url)
    local = Path(local)
    files = [f for f in sorted(local.rglob("*")) if f.is_file()]
    _put_many(fs, files, [f"{root.rstrip('/')}/{f.relative_to(local).as_posix()}" for f in files])
