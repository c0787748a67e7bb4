"""Fuzzing the recipe loader: whatever the input (YAML text, nested data, dotlist overrides), the only exception
that may come out is RecipeError; and every recipe that does validate survives save_resolved -> load_recipe.

Budget: about 15 s on 2 cores (deadline=None: the first call imports the env registry).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import adarl.envs as envs
from adarl.errors import RecipeError
from adarl.runtime.config import Recipe, describe_schema, load_recipe, recipe_to_yaml, validate_recipe

# ADARL_FUZZ_EXAMPLES=5000 for a long hunt; the default keeps the whole file near 15 s
FUZZ = settings(
    max_examples=int(os.environ.get("ADARL_FUZZ_EXAMPLES", "100")),
    deadline=None,
    suppress_health_check=list(HealthCheck),
    database=None,
)


@pytest.fixture(scope="module", autouse=True)
def env_api():
    """The real adarl.envs registry (recipes are validated against it)."""
    real = envs
    assert real is not None and hasattr(real, "SUPPORTED_ENVS")
    yield real


@pytest.fixture(scope="module")
def quick(env_api) -> Recipe:
    return load_recipe("quickstart")


@pytest.fixture(scope="module")
def scratch():
    d = Path(tempfile.mkdtemp(prefix="adarl-fuzz-"))
    yield d
    shutil.rmtree(d, ignore_errors=True)


# ------------------------------------------------------------------------------------------------ strategies

LEAF_PATHS = [row[0] for row in describe_schema()]
KEY_WORDS = sorted(
    {part for path in LEAF_PATHS for part in path.split(".")}
    | {"extends", "kind", "values", "center", "amplitude", "frequency", "phase", "low", "high", "cycle", "torso_length"}
)
SECTIONS = sorted({p.rsplit(".", 1)[0] for p in LEAF_PATHS if "." in p})

keys = st.one_of(st.sampled_from(KEY_WORDS), st.text(max_size=8), st.integers(-3, 3))
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**12), 10**12),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(
        ["auto", "Hopper-v5", "CartPole-v1", "energy", "fixed", "???", "${seed}", "${oc.env:HOME}", "\\${x}"]
    ),
)
nested = st.recursive(
    scalars, lambda ch: st.one_of(st.lists(ch, max_size=4), st.dictionaries(keys, ch, max_size=4)), max_leaves=20
)
value_texts = st.one_of(
    st.text(max_size=15),
    st.sampled_from(
        [
            "0",
            "1",
            "-1",
            "0.5",
            "1e-3",
            "3.5e6",
            "null",
            "true",
            "[]",
            "[32, 32]",
            "[0, 1]",
            "{}",
            "{beta: 0.9}",
            "{kind: fixed, values: {torso_length: 0.3}}",
            "{kind: uniform, low: {x: 1}, high: {x: 0}}",
            ".inf",
            ".nan",
            "'???'",
            "${seed}",
            "${oc.env:HOME}",
            "${",
            "}",
            "[",
            "{",
            "!!python/name:os.system",
            "&a [*a]",
            "fixed",
            "auto",
            "Hopper-v5",
            "cuda:0",
            "'quoted'",
            "- a",
            "a: b",
            "\\${x}",
        ]
    ),
)
override_keys = st.one_of(
    st.sampled_from(LEAF_PATHS + SECTIONS),
    st.builds(lambda p, s: p + s, st.sampled_from(LEAF_PATHS), st.sampled_from([".x", "[0]", "s", ".0", "[9]"])),
    st.text(max_size=12),
)
overrides = st.lists(
    st.one_of(st.builds(lambda k, v: f"{k}={v}", override_keys, value_texts), st.text(max_size=20)), max_size=4
)


def _accept(fn, *args) -> Recipe | None:
    """Run ``fn``; a RecipeError is a fine answer, any other exception fails the test."""
    try:
        out = fn(*args)
    except RecipeError as err:
        assert str(err)  # never an empty message
        return None
    assert isinstance(out, Recipe)
    return out


def _round_trip(recipe: Recipe, path: Path) -> None:
    try:
        text = recipe_to_yaml(recipe)
    except RecipeError:  # only the unrepresentable '???' string
        return
    path.write_text(text, encoding="utf-8")
    back = load_recipe(str(path))
    assert back == recipe


# -------------------------------------------------------------------------------------------------- the fuzz


@FUZZ
@given(doc=st.dictionaries(keys, nested, max_size=8))
def test_random_nested_dicts_validate_or_raise_recipe_error(doc):
    _accept(validate_recipe, doc)


@FUZZ
@given(path=st.sampled_from(LEAF_PATHS + SECTIONS), value=nested)
def test_one_bad_leaf_in_a_valid_recipe(path, value, scratch, quick):
    data = quick.model_dump()
    node = data
    *parents, last = path.split(".")
    for p in parents:
        node = node[p]
    node[last] = value
    r = _accept(validate_recipe, data)
    if r is not None:
        _round_trip(r, scratch / "leaf.yaml")


@FUZZ
@given(text=st.text(max_size=200), extends=st.booleans())
def test_random_yaml_text(text, extends, scratch):
    p = scratch / "text.yaml"
    p.write_text(("extends: quickstart\n" if extends else "") + text, encoding="utf-8")
    _accept(load_recipe, str(p))


@FUZZ
@given(doc=st.dictionaries(keys, nested, max_size=6), extends=st.sampled_from([None, "quickstart", "base", "nosuch"]))
def test_random_yaml_documents(doc, extends, scratch):
    if extends is not None:
        doc = {**doc, "extends": extends}
    try:
        text = yaml.safe_dump(doc, allow_unicode=True)
    except yaml.YAMLError:
        return
    p = scratch / "doc.yaml"
    p.write_text(text, encoding="utf-8")
    r = _accept(load_recipe, str(p))
    if r is not None:
        _round_trip(r, scratch / "doc_rt.yaml")


@FUZZ
@given(ovs=overrides)
def test_random_dotlist_overrides(ovs, scratch):
    r = _accept(load_recipe, "quickstart", ovs)
    if r is not None:
        _round_trip(r, scratch / "ov_rt.yaml")


@FUZZ
@given(description=st.text(max_size=40), name=st.from_regex(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,20}", fullmatch=True))
def test_any_string_round_trips(description, name, scratch, quick):
    r = quick.model_copy(update={"description": description, "name": name})
    if description == "???":
        with pytest.raises(RecipeError):
            recipe_to_yaml(r)
        return
    _round_trip(r, scratch / "str_rt.yaml")
