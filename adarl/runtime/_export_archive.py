"""An exported policy file as bytes: sealed when :mod:`adarl.runtime.export` writes it, checked before anything in
it is loaded (:mod:`adarl.runtime.exported`). Imports torch and the standard library only (and adarl's errors).

**Sealing.** Both formats are zip archives under one root folder. :func:`seal` adds ``<root>/extra/adarl.json``,
the metadata, with ``sha256``: the hash of every other member, so that a changed byte anywhere is found by name.

**Checking** (:func:`read_export`): the file is read once, and only its bytes are used from then on; an empty,
truncated or non-zip file, a member twice, a member whose zip CRC fails, a member missing, added or changed since
export (the manifest) are refused by name with :class:`~adarl.errors.ExportFileError`. A file from before the
manifest loads with a warning, through the same checks otherwise.

**Loading never executes** (:func:`load_program`). The manifest is an integrity check, not a signature: whoever can
rewrite the file can rewrite its manifest, so safety does not rest on it. A TorchScript ``.pt`` is read by
``torch.jit.load``, whose unpickler builds tensors and TorchScript classes only (no Python object, no import). A
``torch.export`` ``.pt2`` is not given to ``torch.export.load`` as it is: that would unpickle its sample inputs and
pickled tensors with ``weights_only=False`` when ``weights_only=True`` fails, ``pickle.loads`` its object
constants, load AOTInductor shared libraries, ``sympy.sympify`` (``eval``) its shape expressions, ``exec`` its guards
and paste its names into generated Python. So the archive is rebuilt in memory from what it may hold and nothing
else: raw tensor payloads; the program's JSON with its debug metadata and guards dropped and every other string
checked (operations: ``torch.ops.aten`` overloads and torch's symbolic-size operators; names: letters, digits,
``_``, ``.``; shape expressions: sympy's integer arithmetic on size symbols); the sample inputs as
``torch.load(weights_only=True)`` reads them, saved again. Anything else is refused by name, unread.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickletools
import re
import stat
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import torch

from adarl.errors import AdaRLWarning, ExportFileError
from adarl.runtime.run_folder._file_safety import why_unloadable

__all__ = ["METADATA_FILE", "MANIFEST_KEY", "ExportArchive", "seal", "read_export", "load_program", "is_export_file"]

#: the metadata file inside an exported archive (``<root>/extra/adarl.json``)
METADATA_FILE = "adarl.json"
#: the metadata key of the manifest: member name (relative to the archive's root folder) -> sha256 hex digest
MANIFEST_KEY = "sha256"
_META_MEMBER = f"extra/{METADATA_FILE}"


def _refuse(path, reason: str) -> ExportFileError:
    return ExportFileError(f"exported policy {str(path)!r} {reason}", path=Path(path), reason=reason)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def seal(data: bytes, metadata: dict) -> bytes:
    """``data`` (a zip ``torch.jit.save`` or ``torch.export.save`` wrote into a buffer, without adarl.json) with
    ``<root>/extra/adarl.json`` added: ``metadata`` and the sha256 of every member (:data:`MANIFEST_KEY`).
    Appended: the members torch wrote (and their alignment) stay byte for byte as they were."""
    buffer = io.BytesIO(data)
    with zipfile.ZipFile(buffer, "a") as z:
        names = z.namelist()
        root = names[0].split("/")[0]
        manifest = {n.split("/", 1)[1]: _sha256(z.read(n)) for n in names}
        z.writestr(f"{root}/{_META_MEMBER}", json.dumps({**metadata, MANIFEST_KEY: manifest}, indent=1))
    return buffer.getvalue()


@dataclass
class ExportArchive:
    """A checked export: its bytes, kind (``'torchscript'`` or ``'export'``), metadata and members by name
    (relative to the root folder), and whether its manifest was checked (False: written before adarl sealed)."""

    path: Path
    data: bytes
    kind: str
    metadata: dict
    members: dict[str, bytes]
    root: str
    sealed: bool


def _read_bytes(path: Path) -> bytes:
    """The file's bytes, read once; a FIFO or device is refused unread (opened non-blocking, checked by fstat)."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise FileNotFoundError(f"{str(path)!r}: no such file") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise _refuse(path, "is not a regular file; refused unread")
        with os.fdopen(fd, "rb") as fh:
            fd = -1
            return fh.read()
    finally:
        if fd >= 0:
            os.close(fd)


def _kind(path: Path, data: bytes) -> str:
    """``'zip'`` or ``'onnx'`` from the first bytes, or refused (empty, or neither)."""
    if not data:
        raise _refuse(path, "is empty (0 bytes): a write or copy cut short; export it again")
    if data[:2] == b"PK":
        return "zip"
    if data[:1] == b"\x08":  # an ONNX ModelProto starts with field 1 (ir_version, a varint)
        return "onnx"
    reason = "is not an exported policy (a TorchScript .pt, torch.export .pt2 or .onnx file)"
    raise ExportFileError(f"{str(path)!r} {reason}", path=path, reason=reason)


def is_export_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` looks like an adarl export (a zip holding ``extra/adarl.json``); never raises."""
    try:
        with zipfile.ZipFile(path) as z:
            return any(n.endswith(f"/{_META_MEMBER}") for n in z.namelist())
    except Exception:  # noqa: BLE001 - a question, not a load
        return False


def read_export(path: str | os.PathLike, *, onnx_ok: bool = False) -> ExportArchive | None:
    """Read and check an export (CRCs, metadata, sha256 manifest); None for an ONNX file when ``onnx_ok``.

    Raises :class:`~adarl.errors.ExportFileError` naming the file and what is wrong with it."""
    p = Path(path)
    data = _read_bytes(p)
    if _kind(p, data) == "onnx":
        if onnx_ok:
            return None
        raise _refuse(p, "is an ONNX file: its metadata is the model's metadata_props['adarl'] (onnx)")
    truncated = (
        "is truncated or corrupt: its zip archive is incomplete (a download or copy cut short?); export it again"
    )
    try:
        z = zipfile.ZipFile(io.BytesIO(data))
        infos = z.infolist()
    except Exception:  # noqa: BLE001 - BadZipFile, or whatever a damaged directory makes zipfile raise
        raise _refuse(p, truncated) from None
    declared = sum(i.file_size for i in infos)
    if declared > 64 * len(data) + (1 << 20):  # torch stores tensors uncompressed: far below this
        raise _refuse(p, f"declares {declared} bytes unpacked from {len(data)} (a zip bomb?); refused unread")
    names = [i.filename for i in infos]
    root = names[0].split("/")[0] if names else ""
    if not root or any(not n.startswith(root + "/") or n == root + "/" for n in names):
        reason = "is a zip archive but not an exported policy (its members are not under one folder)"
        raise ExportFileError(f"{str(p)!r} {reason}", path=p, reason=reason)
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise _refuse(p, f"holds {twice.split('/', 1)[1]} twice (readers would disagree on which one is meant)")
    rel = [n.split("/", 1)[1] for n in names]
    try:
        bad = z.testzip()
    except Exception:  # noqa: BLE001 - a member cut short, an unsupported compression
        raise _refuse(p, truncated) from None
    if bad is not None:
        raise _refuse(
            p,
            f"is corrupt: its {bad.split('/', 1)[1]} fails the zip CRC check (damaged on disk or in a copy); "
            "export it again",
        )
    members = {r: z.read(n) for r, n in zip(rel, names)}
    if "archive_format" in members:
        kind = "export"
    elif "data.pkl" in members:
        kind = "torchscript"
    else:
        reason = "is a zip file but neither a TorchScript nor a torch.export archive"
        raise ExportFileError(f"{str(p)!r} {reason}", path=p, reason=reason)
    if _META_MEMBER not in members:
        raise _refuse(p, f"holds no {METADATA_FILE}: it was not written by adarl export")
    try:
        metadata = json.loads(members[_META_MEMBER].decode("utf-8"))
        if not isinstance(metadata, dict):
            raise ValueError
    except ValueError:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise _refuse(p, f"has a corrupt {METADATA_FILE} (not a JSON object)") from None
    manifest = metadata.get(MANIFEST_KEY)
    if manifest is None:
        warnings.warn(
            f"exported policy {str(p)!r} was written before adarl recorded the sha256 of its contents: damage to it "
            "cannot be detected (it is still loaded without running anything from it); export it again to seal it",
            AdaRLWarning,
            stacklevel=3,
        )
    else:
        _check_manifest(p, manifest, members)
    return ExportArchive(p, data, kind, metadata, members, root, manifest is not None)


def _check_manifest(path: Path, manifest, members: dict[str, bytes]) -> None:
    hexdigest = re.compile(r"[0-9a-f]{64}")
    if not isinstance(manifest, dict) or not all(
        isinstance(k, str) and isinstance(v, str) and hexdigest.fullmatch(v) for k, v in manifest.items()
    ):
        raise _refuse(path, f"has a malformed {MANIFEST_KEY} manifest in its {METADATA_FILE}; export it again")
    present = set(members) - {_META_MEMBER}
    for name in sorted(present - set(manifest)):
        raise _refuse(
            path, f"holds {name}, which was not in it when it was exported (not in its sha256 manifest); refused unread"
        )
    for name in sorted(set(manifest) - present):
        raise _refuse(path, f"has lost {name} since it was exported (it is in its sha256 manifest)")
    for name in sorted(present):
        got = _sha256(members[name])
        if got != manifest[name]:
            raise _refuse(
                path,
                f"was modified or corrupted after export: the sha256 of its {name} is {got[:16]}..., not the "
                f"{manifest[name][:16]}... recorded when it was exported; refused unread, export it again",
            )


# --- loading --------------------------------------------------------------------------------------------------


def load_program(archive: ExportArchive) -> torch.nn.Module:
    """The program of a checked export, loaded without running anything from the file (module docstring)."""
    if archive.kind == "torchscript":
        try:
            with warnings.catch_warnings():  # torch.jit is deprecated in torch 2.x but works (docs/performance.md)
                warnings.filterwarnings("ignore", category=DeprecationWarning, message=r".*torch\.jit.*")
                return torch.jit.load(io.BytesIO(archive.data), map_location="cpu")
        except Exception as err:  # noqa: BLE001 - torch's reader on a damaged or foreign archive
            raise _refuse(archive.path, f"cannot be loaded as a TorchScript program ({_first_line(err)})") from None
    clean = _clean_pt2(archive)
    try:
        program = torch.export.load(io.BytesIO(clean))
        # check_guards=False: the guards would be compiled from strings (dropped from the program above anyway)
        return program.module(check_guards=False)
    except Exception as err:  # noqa: BLE001
        raise _refuse(archive.path, f"cannot be loaded as a torch.export program ({_first_line(err)})") from None


def _first_line(err: BaseException) -> str:
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[0][:200]}" if lines else type(err).__name__


# what a torch.export archive of adarl's may hold (relative to its root folder); anything else is refused unread
_PT2_FIXED = {"archive_format", "archive_version", "byteorder", ".data/version", ".data/serialization_id"}
_PT2_MEMBER = re.compile(
    r"models/model\.json|data/weights/model_weights_config\.json|data/weights/weight_\d+"
    r"|data/constants/model_constants_config\.json|data/constants/tensor_\d+|data/sample_inputs/model\.pt|extra/[\w.-]+"
)
_NAME = re.compile(r"[\w.+-]*")  # every name, key and tag in the program's JSON: no quotes, spaces or brackets
_FQN = re.compile(r"\w+(\.\w+)*")
_ATEN = re.compile(r"torch\.ops\.aten\.(_?[A-Za-z]\w*)\.([A-Za-z]\w*)")
_SYMBOLIC_OPS = {
    *(
        f"_operator.{n}"
        for n in "getitem eq ne le ge lt gt neg pos mul add sub floordiv mod pow truediv and_ or_".split()
    ),
    *(f"torch.sym_{n}" for n in "not int float ite max min sqrt".split()),
    "math.trunc",
}
# sympy's integer arithmetic on size symbols (s0, u1, ...), as torch writes shape expressions
_EXPR_TOKEN = re.compile(r"\s+|\d+|'[a-z]+\d+'|[A-Za-z]\w*|\*\*|//|[-+*/%(),=<>!]")
_EXPR_NAMES = {
    *"Symbol Integer Rational True False positive negative nonnegative nonpositive integer real finite".split(),
    *"Max Min Mod Abs Eq Ne Lt Le Gt Ge And Or Not oo".split(),
    *"FloorDiv CeilDiv CleanDiv ModularIndexing PythonMod IntTrueDiv FloatTrueDiv FloorToInt CeilToInt".split(),
    *"TruncToInt TruncToFloat RoundToInt RoundDecimal ToFloat PowByNatural FloatPow Identity Where".split(),
}
_TREESPEC_TYPES = {None, "builtins.tuple", "builtins.list", "builtins.dict", "collections.OrderedDict"}
_FORBIDDEN_ARGS = {"as_operator", "as_custom_obj", "as_graph"}  # higher-order operators and script objects


def _clean_pt2(archive: ExportArchive) -> bytes:
    """The archive torch.export.load is given: rebuilt from the allowed members, each checked (module docstring)."""
    path, members = archive.path, archive.members

    def refuse(reason: str) -> ExportFileError:
        return _refuse(path, reason + "; refused unread, nothing in it ran")

    for name in members:
        if name not in _PT2_FIXED and not _PT2_MEMBER.fullmatch(name):
            raise refuse(f"holds {name}, which an adarl export never holds (torch.export.load would load it)")
    for needed in ("models/model.json", "data/weights/model_weights_config.json", "archive_version"):
        if needed not in members:
            raise _refuse(path, f"is not a complete torch.export archive: {needed} is missing")
    out: dict[str, bytes] = {}
    for name, data in members.items():
        if name.startswith("extra/") or name == ".data/serialization_id":
            continue  # not needed to load the program (adarl.json was read above)
        if name.endswith("_config.json"):
            _check_payload_config(name, data, members, refuse)
        elif name == "models/model.json":
            data = _clean_program_json(data, refuse)
        elif name == "data/sample_inputs/model.pt":
            data = _plain_sample_inputs(name, data, refuse)
        out[name] = data
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as z:
        for name, data in out.items():
            z.writestr(f"{archive.root}/{name}", data)
    return buffer.getvalue()


def _json(name: str, data: bytes, refuse):
    try:
        return json.loads(data.decode("utf-8"))
    except ValueError:
        raise refuse(f"has a corrupt {name} (not JSON)") from None


def _check_payload_config(name: str, data: bytes, members: dict[str, bytes], refuse) -> None:
    """Tensors stored raw, under a plain name; a pickled tensor or an object constant is refused."""
    config = _json(name, data, refuse)
    entries = config.get("config") if isinstance(config, dict) else None
    if not isinstance(entries, dict):
        raise refuse(f"has a malformed {name}")
    folder = name.rsplit("/", 1)[0]
    for fqn, entry in entries.items():
        where = entry.get("path_name") if isinstance(entry, dict) else None
        if not isinstance(fqn, str) or not _FQN.fullmatch(fqn):
            raise refuse(f"names a tensor {fqn!r} in {name} (names are letters, digits, '_' and '.')")
        if not isinstance(where, str) or f"{folder}/{where}" not in members or entry.get("use_pickle"):
            raise refuse(
                f"stores {fqn} in {name} as {where!r}, not a raw tensor of the archive (a pickled object: "
                "torch.export.load would unpickle it with weights_only=False or pickle.loads)"
            )


def _plain_sample_inputs(name: str, data: bytes, refuse) -> bytes:
    """The sample inputs as ``torch.load(weights_only=True)`` reads them, saved again: torch then reads our bytes."""

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch's pickle-protocol chatter
            inputs = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001
        called = _pickled_callable(data)
        why = (
            f"it holds a Python object ({called}), not only tensors and plain containers"
            if called
            else why_unloadable(err).split("; refused unread")[0]
        )
        raise refuse(f"holds a {name} that is not plain data: {why}") from None
    buffer = io.BytesIO()
    torch.save(inputs, buffer)
    return buffer.getvalue()


def _pickled_callable(data: bytes) -> str | None:
    """The first callable a plain pickle names (``posix.system``), read with pickletools (nothing unpickled); None
    for a torch zip or when none is found."""

    strings: list[str] = []
    try:
        for op, arg, _ in pickletools.genops(io.BytesIO(data)):
            if op.name == "GLOBAL":
                return str(arg).replace(" ", ".")
            if op.name == "STACK_GLOBAL" and len(strings) >= 2:
                return f"{strings[-2]}.{strings[-1]}"
            if isinstance(arg, str):
                strings.append(arg)
    except Exception:  # noqa: BLE001 - not a pickle, or a damaged one
        return None
    return None


def _clean_program_json(data: bytes, refuse) -> bytes:
    """The program's JSON without what torch would execute: debug metadata (its stack traces are pasted into the
    generated code) and guards (exec'd) dropped; every other string checked (module docstring)."""
    program = _json("models/model.json", data, refuse)
    try:
        graph_module = program["graph_module"]
        nodes = graph_module["graph"]["nodes"]
        for node in nodes:
            node["metadata"] = {}
        graph_module["metadata"] = {}
    except (KeyError, TypeError):
        raise refuse("has a malformed models/model.json (no graph)") from None
    guards = program.get("guards_code") or []
    if guards:  # never written for adarl's programs (a batch dimension without bounds)
        raise refuse(f"has guards_code in models/model.json (Python that torch would exec): {str(guards[0])[:80]!r}")
    program["guards_code"] = []
    _check_strings(program, (), refuse)
    return json.dumps(program).encode()


def _check_strings(value, path: tuple, refuse) -> None:
    key = path[-1] if path else None
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str) or not _NAME.fullmatch(k):
                raise refuse(f"has the key {k!r} in models/model.json (names are letters, digits, '_', '.', '+', '-')")
            if k in _FORBIDDEN_ARGS:
                raise refuse(f"has a {k} argument in models/model.json (adarl's programs hold only tensor operations)")
            _check_strings(v, (*path, k), refuse)
    elif isinstance(value, list):
        for v in value:
            _check_strings(v, path, refuse)
    elif isinstance(value, str):
        if key == "target":
            _check_target(value, refuse)
        elif key == "expr_str":
            _check_expression(value, refuse)
        elif key in ("in_spec", "out_spec"):
            _check_treespec(value, refuse)
        elif key == "as_string":
            if not re.fullmatch(r"[\w.+: -]*", value):
                raise refuse(f"has the string argument {value[:80]!r} in models/model.json")
        elif not _NAME.fullmatch(value):
            raise refuse(
                f"has the {key or 'value'} {value[:80]!r} in models/model.json (names are letters, digits, '_', '.', "
                "'+', '-')"
            )


def _check_target(target: str, refuse) -> None:
    """A ``torch.ops.aten`` overload (resolved, and checked to be one) or one of torch's symbolic-size operators."""
    if target in _SYMBOLIC_OPS:
        return
    found = _ATEN.fullmatch(target)
    op = None
    if found:
        try:
            op = getattr(getattr(torch.ops.aten, found.group(1)), found.group(2))
        except (AttributeError, RuntimeError):
            op = None
    if not isinstance(op, torch._ops.OpOverload):
        raise refuse(f"calls {target[:80]!r} in models/model.json, not a torch.ops.aten operation")


def _check_expression(expr: str, refuse) -> None:
    """A shape expression sympy may evaluate: integers, size symbols, arithmetic and sympy's integer functions."""
    pos = 0
    while pos < len(expr):
        token = _EXPR_TOKEN.match(expr, pos)
        word = token.group() if token else expr[pos]
        if token is None or (word[0].isalpha() and word not in _EXPR_NAMES and not re.fullmatch(r"[a-z]+\d+", word)):
            raise refuse(
                f"has the symbolic expression {expr[:80]!r} in models/model.json ({word!r} is not sympy integer "
                "arithmetic; torch would eval it)"
            )
        pos = token.end()


def _check_treespec(spec: str, refuse) -> None:
    """A pytree spec (JSON) of tuples, lists and dicts."""

    def walk(node) -> None:
        if not isinstance(node, dict) or node.get("type") not in _TREESPEC_TYPES:
            raise refuse(f"has an input or output structure {spec[:80]!r} in models/model.json")
        for child in node.get("children_spec") or []:
            walk(child)

    try:
        version, root = json.loads(spec)
    except (ValueError, TypeError):
        raise refuse(f"has a malformed input or output structure {spec[:80]!r} in models/model.json") from None
    walk(root)
