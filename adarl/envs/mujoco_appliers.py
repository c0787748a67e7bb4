"""The appliers: put a ``{parameter: value}`` dict into one live environment, always from its own defaults.

:class:`MujocoDynamics` edits a live ``mujoco.MjModel`` (geometry - recompiled in ``consistent`` mode, the live
arrays in ``ompo`` mode -, mass and friction scales, gravity and wind); :class:`CartPoleDynamics` and
:class:`LinearCartPoleDynamics` set a pole length; a registered env without a MuJoCo model has its parameters'
``apply`` run on the live env. Each keeps a copy of the environment's own defaults and starts every application from
it, so nothing compounds across episodes. Why apart from the registry (:mod:`adarl.envs.registry`): this is the only
part that needs MuJoCo (imported when an applier is built).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping
from typing import Any

import numpy as np

from adarl.envs.declared import FieldSlot, declared_parameters, resolve_field
from adarl.envs.registry import (
    _BODY_MASS_PREFIX,
    _GEOMETRY,
    _MUJOCO_XML,
    _REGISTERED,
    _REQUIRED_NAMES,
    AIR_DENSITY,
    AIR_VISCOSITY,
    _known_envs,
    _unknown,
    check_any_env_id,
    check_mode,
    default_xml_path,
    env_parameters,
    parameters_for,
    quiet_mujoco,
)
from adarl.errors import AdaRLValueError

__all__ = [
    "DynamicsApplier",
    "MujocoDynamics",
    "CartPoleDynamics",
    "LinearCartPoleDynamics",
    "make_applier",
    "COMPILE_CACHE_SIZE",
]


class DynamicsApplier:
    """Applies a ``{parameter: value}`` dict to one live environment, always starting from its defaults."""

    env_id: str
    params: tuple[str, ...]

    def apply(self, values: Mapping[str, float]) -> None:
        raise NotImplementedError

    def restore(self) -> None:
        """Put the environment back to its own defaults."""
        self.apply({})


class CartPoleDynamics(DynamicsApplier):
    """gymnasium CartPole: ``length`` is the half pole length; ``polemass_length = masspole * length``."""

    def __init__(self, unwrapped: Any, env_id: str = "CartPole-v1") -> None:
        for attr in ("length", "masspole", "polemass_length"):
            if not hasattr(unwrapped, attr):
                raise AdaRLValueError(
                    f"{env_id}: the live environment {type(unwrapped).__name__} has no attribute {attr!r}; "
                    "expected gymnasium's CartPoleEnv"
                )
        self.env_id = env_id
        self.env = unwrapped
        self.params = ("pole_length",)
        self.default_length = float(unwrapped.length)

    def apply(self, values: Mapping[str, float]) -> None:
        length = float(values.get("pole_length", self.default_length))
        self.env.length = length
        self.env.polemass_length = self.env.masspole * length


class LinearCartPoleDynamics(DynamicsApplier):
    """adarl's :class:`~adarl.envs.linear_cartpole.LinearCartPoleEnv`: ``pole_length`` via ``set_pole_length``."""

    def __init__(self, env: Any, env_id: str = "LinearCartPole-v0") -> None:
        if not hasattr(env, "set_pole_length"):
            raise AdaRLValueError(
                f"{env_id}: the live environment {type(env).__name__} has no set_pole_length(); "
                "expected adarl.envs.LinearCartPoleEnv"
            )
        self.env_id = env_id
        self.env = env
        self.params = ("pole_length",)

    def apply(self, values: Mapping[str, float]) -> None:
        self.env.set_pole_length(values.get("pole_length"))


# Fields restored from the default snapshot before every application, and copied from a recompiled model in
# ``consistent`` mode (everything the compiler derives from the geometry; mj_setConst derives the rest).
_GEOMETRY_FIELDS = (
    "body_pos",
    "body_quat",
    "body_ipos",
    "body_iquat",
    "body_mass",
    "body_inertia",
    "geom_size",
    "geom_pos",
    "geom_quat",
    "geom_rbound",
    "geom_aabb",
    "bvh_aabb",
)
_OTHER_FIELDS = ("geom_friction",)
_OPT_FIELDS = ("gravity", "wind", "density", "viscosity")


class _ModelEditor:
    """Geometry edits on the live model's arrays (OMPO's way: mass and inertia stay as compiled)."""

    def __init__(self, model: Any, defaults: Mapping[str, np.ndarray]) -> None:
        self.model = model
        self.defaults = defaults

    def _element(self, kind: str, name: str) -> Any:
        try:
            return self.model.body(name) if kind == "body" else self.model.geom(name)
        except KeyError:
            raise AdaRLValueError(f"the model has no {kind} named {name!r}") from None

    def set_body_z(self, body: str, z: float) -> None:
        self._element("body", body).pos[2] = z

    def set_half_length(self, geom: str, value: float) -> None:
        self._element("geom", geom).size[1] = value

    def scale_along(self, geom: str, factor: float) -> None:
        g = self._element("geom", geom)
        g.size[1] = self.defaults["geom_size"][g.id][1] * factor
        g.pos[:] = self.defaults["geom_pos"][g.id] * factor


class _SpecEditor:
    """The same edits on an ``MjSpec`` of the model's XML (values set absolutely from the spec's originals)."""

    def __init__(self, spec: Any) -> None:
        self.spec = spec
        self.original: dict[tuple[str, str], np.ndarray] = {}

    def _element(self, kind: str, name: str) -> Any:
        element = self.spec.body(name) if kind == "body" else self.spec.geom(name)
        if element is None:
            raise AdaRLValueError(f"the model has no {kind} named {name!r}")
        return element

    def _orig(self, kind: str, name: str, attr: str) -> np.ndarray:
        key = (kind, name + "/" + attr)
        if key not in self.original:
            self.original[key] = np.array(getattr(self._element(kind, name), attr), dtype=float)
        return self.original[key]

    def set_body_z(self, body: str, z: float) -> None:
        pos = self._orig("body", body, "pos").copy()
        pos[2] = z
        self._element("body", body).pos = pos

    def set_half_length(self, geom: str, value: float) -> None:
        size = self._orig("geom", geom, "size").copy()
        size[1] = value
        self._element("geom", geom).size = size

    def scale_along(self, geom: str, factor: float) -> None:
        fromto = self._orig("geom", geom, "fromto")
        element = self._element("geom", geom)
        if np.isfinite(fromto).all():  # defined by its end points: scale them about the body origin
            element.fromto = fromto * factor
        else:
            element.size = self._orig("geom", geom, "size") * np.array([1.0, factor, 1.0])
            element.pos = self._orig("geom", geom, "pos") * factor

    def reset(self) -> None:
        for (kind, key), value in self.original.items():
            name, attr = key.rsplit("/", 1)
            setattr(self._element(kind, name), attr, value.copy())


#: Bound on the number of recompiled models kept per environment in ``consistent`` mode.
COMPILE_CACHE_SIZE = 256

LINEAR_ID = "LinearCartPole-v0"


class MujocoDynamics(DynamicsApplier):
    """Edits a live ``mujoco.MjModel`` of a gymnasium MuJoCo environment.

    Every :meth:`apply` first restores the defaults captured at construction (so nothing compounds), then:
    geometry (``consistent``: an ``MjSpec`` of the XML is edited, compiled - cached per value set - and its
    geometry, mass and inertia arrays copied in; ``ompo``: the live arrays are edited as OMPO does), mass and
    friction scales, gravity and wind, the parameters a recipe declares (``declared``: ``env.parameters``, each
    one entry of a model field, set absolutely; resolved against this model here, so a bad index or name fails
    when the env is built), and finally ``mj_setConst`` on a scratch ``MjData`` (fresh bounding radii, so
    contacts stay valid, and consistent derived constants; the env's own data is untouched).
    """

    def __init__(
        self,
        model: Any,
        env_id: str,
        params: tuple[str, ...],
        mode: str = "consistent",
        xml_path: str | None = None,
        declared: Mapping[str, Any] | None = None,
    ) -> None:
        import mujoco

        self._mujoco = mujoco
        self.env_id = check_any_env_id(env_id)
        self.mode = check_mode(mode)
        self.model = model
        self.params = tuple(params)
        self.xml_path = xml_path or (default_xml_path(env_id) if env_id in _MUJOCO_XML else None)
        allowed = parameters_for(env_id, declared, require=params)
        fields = {n: p for n, p in declared_parameters(declared).items() if n in self.params}
        self._declared: dict[str, FieldSlot] = {n: resolve_field(model, p) for n, p in fields.items()}
        self._declared_defaults = {n: slot.get() for n, slot in self._declared.items()}
        live_bodies = {model.body(i).name for i in range(1, model.nbody)} - {""}
        self._body_ids: dict[str, int] = {}
        for name in self.params:
            if name.startswith(_BODY_MASS_PREFIX):
                body = name[len(_BODY_MASS_PREFIX) :]
                if body not in live_bodies:
                    raise AdaRLValueError(
                        f"unknown parameter {name!r} for {env_id}: the model has no body {body!r}; "
                        f"allowed bodies: {sorted(live_bodies)}"
                    )
                self._body_ids[name] = model.body(body).id
            elif name not in allowed:
                raise _unknown(env_id, name, allowed)
        self._fields = tuple(f for f in _GEOMETRY_FIELDS if hasattr(model, f))  # bvh_aabb: newer MuJoCo only
        self.defaults = {f: np.array(getattr(model, f), copy=True) for f in self._fields + _OTHER_FIELDS}
        self.default_opt = {f: np.array(getattr(model.opt, f), copy=True) for f in _OPT_FIELDS}
        self.geometry = {p: e for p, e in _GEOMETRY.get(self.env_id, {}).items() if p in self.params}
        self._geo_defaults = self._geometry_defaults()
        self.uses_air = "wind" in self.params
        self._scratch = mujoco.MjData(model)
        self._spec: Any = None
        self._spec_editor: _SpecEditor | None = None
        self._cache: OrderedDict[tuple, dict[str, np.ndarray]] = OrderedDict()
        self.compiles = 0  # how many models were compiled (for tests and diagnostics)

    def _geometry_defaults(self) -> dict[str, float]:
        """What the edits get as ``defaults``: every parameter's default, and the built-in edits' own numbers."""
        m = self.model
        if not self.geometry:
            return {}
        out = {n: p.default for n, p in env_parameters(self.env_id).items() if not n.startswith(_BODY_MASS_PREFIX)}
        bodies, geoms = _REQUIRED_NAMES.get(self.env_id, ((), ()))
        try:
            for name in bodies:
                m.body(name)
            for name in geoms:
                m.geom(name)
        except KeyError as err:
            raise AdaRLValueError(
                f"{self.env_id}: the live model lacks a body or geom the geometry parameters "
                f"{sorted(self.geometry)} need ({err}); they need the gymnasium v5 model "
                f"(bodies {list(bodies)}, geoms {list(geoms)})"
            ) from err
        if "torso" in bodies:
            out["torso_z"] = float(m.body("torso").pos[2])
            out["torso_half"] = float(m.geom("torso_geom").size[1])
        return out

    def _edit(self, editor: Any, name: str, value: float) -> None:
        try:
            self.geometry[name](editor, value, self._geo_defaults)
        except AdaRLValueError as err:
            raise AdaRLValueError(f"{self.env_id}: parameter {name} = {value!r}: {err}") from err
        except Exception as err:  # noqa: BLE001 - a registered parameter's own code, named with its parameter
            raise AdaRLValueError(
                f"{self.env_id}: applying parameter {name} = {value!r} failed: {type(err).__name__}: {err}"
            ) from err

    def _is_default(self, name: str, value: float) -> bool:
        return abs(value - env_parameters(self.env_id)[name].default) <= 1e-12

    def _compiled(self, geo: dict[str, float]) -> dict[str, np.ndarray]:
        key = tuple(sorted(geo.items()))
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        mujoco = self._mujoco
        if self._spec is None:
            with quiet_mujoco():
                self._spec = mujoco.MjSpec.from_file(self.xml_path)
            self._spec_editor = _SpecEditor(self._spec)
        editor = self._spec_editor
        editor.reset()
        for name, value in geo.items():
            self._edit(editor, name, value)
        with quiet_mujoco():
            compiled = self._spec.compile()
        self.compiles += 1
        arrays = {}
        for f in self._fields:
            new, live = getattr(compiled, f), getattr(self.model, f)
            if new.shape != live.shape:
                raise AdaRLValueError(
                    f"{self.env_id}: the model recompiled from {self.xml_path} does not match the live model "
                    f"({f} has shape {new.shape}, live {live.shape}); use mode='ompo' for a customised model"
                )
            arrays[f] = np.array(new, copy=True)
        self._cache[key] = arrays
        if len(self._cache) > COMPILE_CACHE_SIZE:
            self._cache.popitem(last=False)
        return arrays

    def apply(self, values: Mapping[str, float]) -> None:
        mujoco, model = self._mujoco, self.model
        for f, default in self.defaults.items():
            getattr(model, f)[...] = default
        for f, default in self.default_opt.items():
            if default.ndim:
                getattr(model.opt, f)[:] = default
            else:
                setattr(model.opt, f, float(default))

        geo = {p: float(values[p]) for p in self.geometry if p in values and not self._is_default(p, values[p])}
        if geo:
            if self.mode == "consistent":
                for f, array in self._compiled(geo).items():
                    getattr(model, f)[...] = array
            else:
                editor = _ModelEditor(model, self.defaults)
                for name, value in geo.items():
                    self._edit(editor, name, value)

        scale = np.ones(model.nbody)
        if "mass_scale" in values:
            scale *= float(values["mass_scale"])
        for name, body_id in self._body_ids.items():
            if name in values:
                scale[body_id] *= float(values[name])
        if (scale != 1.0).any():
            model.body_mass[:] *= scale
            model.body_inertia[:] *= scale[:, None]
        if "friction_scale" in values:
            model.geom_friction[:] *= float(values["friction_scale"])
        if "gravity" in values:
            model.opt.gravity[:] = (0.0, 0.0, -float(values["gravity"]))
        if self.uses_air:
            model.opt.density = AIR_DENSITY
            model.opt.viscosity = AIR_VISCOSITY
            model.opt.wind[:] = (-float(values.get("wind", 0.0)), 0.0, 0.0)
        for name, slot in self._declared.items():  # restored first (outside the fields above), then set
            slot.set(float(values.get(name, self._declared_defaults[name])))
        mujoco.mj_setConst(model, self._scratch)


class _LiveEnvDynamics(DynamicsApplier):
    """A registered env without a MuJoCo model file: each parameter's ``apply(env, value, defaults)`` on the live
    (unwrapped) gymnasium env, every time with every parameter (its default when not given), so nothing compounds.
    """

    def __init__(self, unwrapped: Any, env_id: str, params: tuple[str, ...]) -> None:
        allowed = env_parameters(env_id, require=params)
        for name in params:
            if name not in allowed:
                raise _unknown(env_id, name, allowed)
        self.env_id = env_id
        self.env = unwrapped
        self.params = tuple(params)
        self.edits = {p: _GEOMETRY[env_id][p] for p in self.params}
        self.defaults = {n: p.default for n, p in allowed.items()}

    def apply(self, values: Mapping[str, float]) -> None:
        for name, edit in self.edits.items():
            value = float(values.get(name, self.defaults[name]))
            try:
                edit(self.env, value, self.defaults)
            except AdaRLValueError:
                raise
            except Exception as err:  # noqa: BLE001 - a registered parameter's own code, named with its parameter
                raise AdaRLValueError(
                    f"{self.env_id}: applying parameter {name} = {value!r} failed: {type(err).__name__}: {err}"
                ) from err


def make_applier(
    env_id: str,
    unwrapped: Any,
    params: tuple[str, ...],
    mode: str = "consistent",
    declared: Mapping[str, Any] | None = None,
) -> DynamicsApplier:
    """The applier for a live (unwrapped) gymnasium environment; ``declared``: the recipe's ``env.parameters``
    (MuJoCo model fields: the env must simulate with MuJoCo)."""
    env_id = check_any_env_id(env_id)
    check_mode(mode)
    model = getattr(unwrapped, "model", None)
    if declared and (model is None or not hasattr(model, "body_mass") or env_id in ("CartPole-v1", LINEAR_ID)):
        raise AdaRLValueError(
            f"env.parameters {sorted(declared)} map onto MuJoCo model fields, but {env_id}'s live environment "
            f"{type(unwrapped).__name__} has no MuJoCo model (`.model`); declared parameters need a MuJoCo env "
            "(e.g. a gymnasium '-v5' MuJoCo env)"
        )
    if env_id == "CartPole-v1":
        return CartPoleDynamics(unwrapped, env_id)
    if env_id == LINEAR_ID:
        return LinearCartPoleDynamics(unwrapped, env_id)
    if env_id in _REGISTERED and env_id not in _MUJOCO_XML:
        return _LiveEnvDynamics(unwrapped, env_id, params)
    if model is None or not hasattr(model, "body_mass"):
        raise AdaRLValueError(
            f"{env_id}: the live environment {type(unwrapped).__name__} has no MuJoCo model (`.model`); "
            f"supported: {list(_known_envs())}"
        )
    return MujocoDynamics(model, env_id, params, mode, xml_path=getattr(unwrapped, "fullpath", None), declared=declared)
