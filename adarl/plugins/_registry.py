"""The generic :class:`Registry` and the ``adarl.plugins`` entry-point group: what every name-based extension point
of adarl is built on (lookup by name, the unknown-name error, plugin loading, provenance). Private module of
:mod:`adarl.plugins`."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from importlib import metadata
from importlib.metadata import entry_points
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict

from adarl.errors import AdaRLValueError, UnknownNameError, did_you_mean, one_of

#: the entry-point group installed packages declare their plugins in
ENTRY_POINT_GROUP = "adarl.plugins"

# =====================================================================================================================
# Entry points and provenance
# =====================================================================================================================

_loaded: set[str] = set()  # entry points already loaded (by "name = value")
_current_provider: list[str | None] = [None]
Plugin = Callable[[], None]  # a callable that registers (the value of a "module:function" entry point)


def load_entry_points() -> None:
    """Load every ``adarl.plugins`` entry point not loaded yet: a module is imported, a function is called. A
    plugin that fails to load is an error naming it (a half-registered plugin would run as something else)."""
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        key = f"{ep.name} = {ep.value}"
        if key in _loaded:
            continue
        _loaded.add(key)
        dist = getattr(getattr(ep, "dist", None), "name", None)
        try:
            with providing(dist):
                obj = ep.load()
                if callable(obj) and not isinstance(obj, type):
                    obj()
        except (Exception, SystemExit) as err:  # noqa: BLE001 - any failure of third-party code, named with it;
            # SystemExit too: a plugin calling sys.exit() at import would otherwise end the run with status 0, silently
            raise AdaRLValueError(
                f"the adarl plugin {ep.name!r} ({ep.value}, package {dist or '?'}) failed to load: "
                f"{type(err).__name__}: {err}"
            ) from err


@contextmanager
def providing(provider: str | None):
    """Registrations made inside record ``provider`` (an entry point's distribution, a recipe's local module)."""
    previous, _current_provider[0] = _current_provider[0], provider
    try:
        yield
    finally:
        _current_provider[0] = previous


def current_provider() -> str | None:
    """The distribution whose entry point is loading now: what a registration records as its entry's ``provider``
    (None outside an entry point: adarl's own entries, and those registered in-process)."""
    return _current_provider[0]


def provenance(provider: str | None) -> dict:
    """``{"package", "version"}`` of an entry's provider: the distribution and its installed version, or adarl's."""
    package = provider or "adarl"
    try:
        version = metadata.version(package)
    except metadata.PackageNotFoundError:
        version = None
    return {"package": package, "version": version}


# =====================================================================================================================
# The registry
# =====================================================================================================================

T = TypeVar("T")


class Registry(Generic[T]):
    """Entries by name: what every extension point of adarl is (see the module docstring).

    Args:
        key: what a name is called in messages (``"algorithm.name"``, ``"rank.rule"``, ``"init scheme"``).
        what: what an entry is called in messages about registering (``"algorithm"``; default: ``key``).
        how: how to register one, ending the unknown-name error (None: the error lists the allowed names only).
        plugins: whether a name not known yet loads the installed plugins' entry points before the error.
        order: how names are listed (``sorted``; ``list``: the order they were registered in).
        entries: the dict of entries (default: a new one), or a callable returning it at each call (tests swap it).
        describe: an entry in the name-taken error (``"loss torchrl.objectives:SACLoss, from adarl"``).
        same: whether a registration under a taken name is the same entry again (then allowed without ``replace``).
        protected: names that can never be registered again (adarl's own rank rules).
        noun: what to pick another of, in the name-taken error (``"name"``, ``"id"``).
    """

    def __init__(
        self,
        key: str,
        *,
        what: str | None = None,
        how: str | None = None,
        plugins: bool = True,
        order: Callable[[Iterable[str]], list[str]] = sorted,
        entries: dict[str, T] | Callable[[], dict[str, T]] | None = None,
        describe: Callable[[T], str] | None = None,
        same: Callable[[T, T], bool] | None = None,
        protected: Iterable[str] = (),
        noun: str = "name",
    ) -> None:
        self.key, self.what, self.how, self.plugins, self.order = key, what or key, how, plugins, order
        store = {} if entries is None else entries
        self._entries = store if callable(store) else (lambda: store)
        self.describe, self.same, self.protected, self.noun = describe, same, tuple(protected), noun

    @property
    def entries(self) -> dict[str, T]:
        """``{name: entry}`` as registered (nothing loaded)."""
        return self._entries()

    def __contains__(self, name: object) -> bool:
        return name in self.entries

    def load(self) -> None:
        """Load the installed plugins' entry points (when this registry takes plugins)."""
        if self.plugins:
            load_entry_points()

    def names(self, *, load: bool = True) -> list[str]:
        """The registered names, in :attr:`order` (``load``: the installed plugins' entry points first)."""
        if load:
            self.load()
        return list(self.order(self.entries))

    def get(self, name: str) -> T:
        """The entry registered as ``name``; installed plugins are loaded when it is not known yet, and an unknown
        name is an :class:`~adarl.errors.UnknownNameError` listing the registered ones (:meth:`unknown`)."""
        if name not in self.entries:
            self.load()
        if name not in self.entries:
            raise self.unknown(name)
        return self.entries[name]

    def unknown(self, name: Any) -> UnknownNameError:
        """The error for a name nobody registered: the allowed names, a close one, and how to register (typed:
        ``kind``, ``name`` and ``allowed`` are attributes too)."""
        names = list(self.order(self.entries))
        plugin = "no installed plugin registers it; " if self.plugins else ""
        where = "" if self.how is None else f" ({plugin}{self.how})"
        return UnknownNameError(
            f"unknown {self.key} {name!r}; allowed: {one_of(names)}{did_you_mean(str(name), names)}{where}",
            kind=self.key,
            name=name,
            allowed=names,
            hint=where,
        )

    def check_free(self, name: str, entry: T | None = None, *, replace: bool = False) -> None:
        """Refuse a taken ``name`` (unless ``replace``, or :attr:`same` says ``entry`` is the one registered), and
        a :attr:`protected` one always: before anything is registered."""
        old = self.entries.get(name)
        if old is not None and name in self.protected:
            raise AdaRLValueError(
                f"{self.what} {name!r} is one of adarl's own ({one_of(self.protected)}) and cannot be replaced; "
                f"pick another {self.noun}"
            )
        again = entry is not None and self.same is not None and old is not None and self.same(old, entry)
        if old is not None and not replace and not again:
            detail = f" ({self.describe(old)})" if self.describe is not None else ""
            raise AdaRLValueError(
                f"{self.what} {name!r} is already registered{detail}; pick another {self.noun} or pass replace=True"
            )

    def provenance(self, name: str) -> dict:
        """Where the entry registered as ``name`` came from (its ``provider``, :func:`provenance`): plugins.json's."""
        return provenance(getattr(self.get(name), "provider", None))

    def register(self, name: str, entry: T, *, replace: bool = False) -> T:
        """Add ``entry`` as ``name`` (:meth:`check_free` first); returns it."""
        self.check_free(name, entry, replace=replace)
        self.entries[name] = entry
        return entry


class NoOptions(BaseModel):
    """The options of an algorithm that has none: ``algorithm.options`` must stay empty."""

    model_config = ConfigDict(extra="forbid")


def _path_of(obj: Any) -> str:
    return obj if isinstance(obj, str) else f"{obj.__module__}:{obj.__qualname__}"


def _resolve(obj: Any) -> Any:
    """``obj``, or the object a ``"module:attr.attr"`` path names (imported now)."""
    if not isinstance(obj, str):
        return obj
    module, _, attr = obj.partition(":")
    out = importlib.import_module(module)
    for part in attr.split("."):
        out = getattr(out, part)
    return out
