"""A time the reproduction states for a commit is that commit's own, read from git (issue 45: stated amendment times
had run 17-21 minutes after their commits, so a reader could not tell which results were known when a protocol
changed). Every "<sha> ... <date> <HH:MM> UTC" in docs/reproduction.md and README.md must equal the commit's
committer time in UTC, to the minute; and a verdict or amendment is dated by its commit, never "written <date>
~<time>"."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("docs/reproduction.md", "README.md")
#: a short or full sha, then within 40 characters (no parenthesis between) the date and minute it was committed
STATED = re.compile(r"\b([0-9a-f]{7,40})\b[^()]{0,40}?(\d{4}-\d\d-\d\d)[ T](\d\d:\d\d)(?::\d\d)? UTC")
APPROXIMATE = re.compile(r"written \d{4}-\d\d-\d\d ~")


def _git(*args: str) -> str:
    env = {**os.environ, "TZ": "UTC"}
    return subprocess.run(["git", *args], cwd=ROOT, env=env, capture_output=True, text=True, check=True).stdout.strip()


def _stated() -> list[tuple[str, str, str]]:
    """``(file, sha, "YYYY-MM-DD HH:MM")`` of every commit time the docs state (line breaks read as spaces)."""
    out = []
    for name in DOCS:
        text = re.sub(r"\s+", " ", (ROOT / name).read_text())
        out += [(name, m[1], f"{m[2]} {m[3]}") for m in STATED.finditer(text)]
    return out


def test_stated_commit_times_are_the_commits_own():
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout (an sdist or a copied tree): the commits' times cannot be read")
    if _git("rev-parse", "--is-shallow-repository") == "true":
        pytest.skip("a shallow clone lacks the stated commits")
    stated = _stated()
    assert len(stated) >= 15, f"the pattern found only {len(stated)} stated commit times: is it still the docs' form?"
    wrong = []
    for name, sha, when in stated:
        try:
            actual = _git("log", "-1", "--format=%cd", "--date=format-local:%Y-%m-%d %H:%M", sha)
        except subprocess.CalledProcessError:
            wrong.append(f"{name}: {sha} is not a commit of this repository")
            continue
        if actual != when:
            wrong.append(f"{name}: {sha} stated at {when} UTC, committed at {actual} UTC")
    assert not wrong, "\n".join(wrong)


def test_verdicts_and_amendments_are_dated_by_their_commit():
    loose = [
        f"{name}: ...{m.group(0)}..."
        for name in DOCS
        for m in APPROXIMATE.finditer(re.sub(r"\s+", " ", (ROOT / name).read_text()))
    ]
    assert not loose, "date these by their commit ('written in <sha>, <date> <HH:MM> UTC from git'):\n" + "\n".join(
        loose
    )
