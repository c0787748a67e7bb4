"""Training callbacks by name: the entries of a recipe's ``callbacks`` list (:func:`register_callback`,
:func:`callback`) and adarl's own. Private module of :mod:`adarl.plugins`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from adarl.errors import AdaRLValueError
from adarl.plugins._registry import (
    ENTRY_POINT_GROUP,
    NoOptions,
    Registry,
    _path_of,
    _resolve,
    current_provider,
    provenance,
)

# =====================================================================================================================
# Training callbacks by name: each entry of a recipe's ``callbacks`` list is looked up as ``algorithm.name`` is, and
# its ``options`` validated by the callback's pydantic model. A callback is a TorchRL ``TrainerHookBase``-style
# object (:class:`adarl.runtime.callbacks.Callback`), built with its options as keyword arguments (docs/callbacks.md).
# =====================================================================================================================

#: adarl's own callbacks (their names cannot be registered again)
BUILTIN_CALLBACKS = ("stop_on_return",)
HOW_TO_REGISTER_CALLBACK = (
    "register one with adarl.register_callback(...) in a module the recipe's plugins list names, or in a package "
    f"that declares an {ENTRY_POINT_GROUP!r} entry point (docs/callbacks.md)"
)


class StopOnReturnOptions(BaseModel):
    """``options`` of the ``stop_on_return`` callback (SB3's ``StopTrainingOnRewardThreshold``)."""

    model_config = ConfigDict(extra="forbid")
    threshold: float = Field(
        allow_inf_nan=False, description="stop after the first evaluation whose mean return is >= this"
    )
    min_frames: int = Field(0, ge=0, description="no stop before this many frames, whatever the return")


@dataclass(frozen=True)
class CallbackSpec:
    """A registered callback name (an entry of a recipe's ``callbacks``).

    ``callback``: the class (a subclass of :class:`adarl.runtime.callbacks.Callback`, or any TorchRL
    ``TrainerHookBase`` with ``register``, ``state_dict`` and ``load_state_dict``), or a ``"module:Class"`` path
    imported when a run is built (this module imports no torch). ``options``: a pydantic model of the entry's
    ``options``, which the class is built with as keyword arguments. ``provider``: the distribution whose entry point
    registered it (None for adarl's own and for a recipe's local module, which plugins.json records by sha256)."""

    name: str
    callback: Any
    options: type[BaseModel] = NoOptions
    description: str = ""
    provider: str | None = None
    builtin: bool = False

    @property
    def callback_path(self) -> str:
        return _path_of(self.callback)

    def callback_class(self) -> type:
        """The callback class (a ``"module:Class"`` path is imported now; a failure is an error naming it)."""
        try:
            return _resolve(self.callback)
        except (ImportError, AttributeError) as err:
            raise AdaRLValueError(
                f"callback {self.name!r} (from {self.provider or 'adarl'}) names {self.callback!r}, which cannot be "
                f"imported: {type(err).__name__}: {err}"
            ) from err

    def provenance(self) -> dict:
        """Where this name came from (the run folder's plugins.json): the class, the package and its version."""
        return {"name": self.name, "callback": self.callback_path, **provenance(self.provider)}


_callbacks: dict[str, CallbackSpec] = {}
CALLBACKS: Registry[CallbackSpec] = Registry(
    "callbacks.name",
    what="callback",
    how=HOW_TO_REGISTER_CALLBACK,
    order=list,
    entries=lambda: _callbacks,
    describe=lambda old: f"class {old.callback_path}, from {old.provider or 'adarl'}",
    same=lambda old, new: old.callback_path == new.callback_path,
    protected=BUILTIN_CALLBACKS,
)


def register_callback(
    name: str,
    callback: Any = None,
    *,
    options: type[BaseModel] | None = None,
    description: str = "",
    replace: bool = False,
):
    """Register a recipe's ``callbacks: [{name: <name>, options: {...}}]``; usable as a class decorator::

        class EveryNOptions(BaseModel):
            model_config = ConfigDict(extra="forbid")
            n: int = Field(100, ge=1)

        @register_callback("every_n", options=EveryNOptions)
        class EveryN(Callback):
            def __init__(self, n: int = 100): ...
            def post_optim(self, losses): ...

    A name registered twice is an error (``replace=True`` to override on purpose); adarl's own cannot be replaced."""
    if not isinstance(name, str) or not name.isidentifier():
        raise AdaRLValueError(f"callback name must be an identifier (letters, digits, _), got {name!r}")
    if options is not None and not (isinstance(options, type) and issubclass(options, BaseModel)):
        raise AdaRLValueError(
            f"register_callback({name!r}): options must be a pydantic BaseModel class, got {options!r}"
        )

    def _register(cls):
        if not isinstance(cls, (str, type)):
            raise AdaRLValueError(
                f"register_callback({name!r}): callback must be a class or a 'module:Class' path, got {cls!r}"
            )
        entry = CallbackSpec(
            name=name,
            callback=cls,
            options=options or NoOptions,
            description=description,
            provider=current_provider(),
            builtin=name in BUILTIN_CALLBACKS,
        )
        CALLBACKS.register(name, entry, replace=replace)
        return cls

    if callback is None:
        return _register
    return _register(callback)


def callback_names(*, load: bool = True) -> list[str]:
    """The registered callback names, adarl's own first (``load``: installed plugins first)."""
    return CALLBACKS.names(load=load)


def callback(name: str) -> CallbackSpec:
    """The :class:`CallbackSpec` registered as ``name``; installed plugins are loaded when it is not known yet.

    >>> callback("stop_on_return").callback_path
    'adarl.runtime.callbacks:StopOnReturn'
    >>> callback("stop_on_retrun")
    Traceback (most recent call last):
        ...
    adarl.errors.UnknownNameError: unknown callbacks.name 'stop_on_retrun'; allowed: 'stop_on_return'; did you mean ...
    """
    return CALLBACKS.get(name)


register_callback(
    "stop_on_return",
    "adarl.runtime.callbacks:StopOnReturn",
    options=StopOnReturnOptions,
    description="stop training after the evaluation whose mean return reaches options.threshold",
)
