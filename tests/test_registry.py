"""The generic registry every name-based extension point of adarl is (adarl.plugins.Registry): lookup, the unknown
name's error (allowed names, a close one, how to register), installed plugins loaded first, a taken name refused
unless replace (or the same entry again), protected names, the entries' store read at every call, provenance."""

from __future__ import annotations

import pytest

from adarl import plugins
from adarl.errors import AdaRLValueError
from adarl.plugins import Registry, provenance


def _registry(**kwargs) -> Registry:
    kwargs.setdefault("how", "register one with register_thing(...)")
    return Registry("thing.name", what="thing", plugins=False, **kwargs)


def test_lookup_and_the_unknown_names_error():
    reg = _registry()
    reg.register("alpha", 1)
    reg.register("beta", 2)
    assert reg.get("beta") == 2 and "alpha" in reg and "gamma" not in reg and reg.names() == ["alpha", "beta"]
    with pytest.raises(AdaRLValueError) as info:
        reg.get("alpah")
    assert str(info.value) == (
        "unknown thing.name 'alpah'; allowed: 'alpha', 'beta'; did you mean 'alpha'? "
        "(register one with register_thing(...))"
    )
    plain = Registry("init scheme", plugins=False, order=list)
    plain.register("default", None)
    with pytest.raises(AdaRLValueError, match=r"^unknown init scheme 'x'; allowed: 'default'$"):
        plain.get("x")


def test_a_taken_name_is_refused_unless_replace_or_the_same_entry():
    reg = _registry(describe=lambda old: f"value {old}", same=lambda old, new: old == new)
    reg.register("alpha", 1)
    reg.register("alpha", 1)  # the same entry again: fine
    with pytest.raises(AdaRLValueError, match=r"thing 'alpha' is already registered \(value 1\); .*replace=True"):
        reg.register("alpha", 2)
    reg.register("alpha", 2, replace=True)
    assert reg.get("alpha") == 2


def test_protected_names_are_never_registered_again():
    reg = _registry(protected=("alpha",))
    reg.register("alpha", 1)
    with pytest.raises(AdaRLValueError, match="thing 'alpha' is one of adarl's own .* cannot be replaced"):
        reg.register("alpha", 1, replace=True)


def test_an_unknown_name_loads_the_installed_plugins_first(monkeypatch):
    reg = Registry("thing.name", how="how")
    monkeypatch.setattr(plugins._registry, "load_entry_points", lambda: reg.entries.setdefault("late", 3))
    assert reg.get("late") == 3


def test_the_store_is_read_at_every_call():
    stores = [{"alpha": 1}]
    reg = Registry("thing.name", plugins=False, entries=lambda: stores[-1])
    # a test swaps a copy in, as monkeypatch.setattr(plugins._algorithm, "_algorithms", ...) does
    stores.append({"beta": 2})
    assert reg.names() == ["beta"]


def test_provenance_names_the_package_and_its_version():
    assert provenance(None)["package"] == "adarl"
    assert provenance("no-such-distribution-xyz") == {"package": "no-such-distribution-xyz", "version": None}
    assert plugins.ALGORITHMS.provenance("sac") == provenance(None)
    record = plugins.algorithm("sac").provenance()
    assert list(record) == ["name", "base", "loss", "package", "version"] and record["package"] == "adarl"
