"""Every Python example in the documentation runs.

Which files: every ``docs/**/*.md`` and the top-level ``README.md`` (if present), found at collection time, so a
new page is picked up without touching this test. One test per file.

Which blocks: fenced code blocks whose info string starts with ``python`` (or ``py``/``python3``), fenced with
backticks or tildes, at any indentation. All of a file's blocks run IN ORDER in ONE fresh namespace, so a later
block may use names an earlier one defined. Blocks that are not meant to run (they need a GPU, a long training
run, a file that does not exist...) are marked in the info string with ``no-run``::

    ```python no-run
    trainer.train()   # shown, never executed
    ```

(``norun``/``no_run``/``skip`` are accepted too.) Other languages (``bash``, ``yaml``, ``pycon``, ``text``) are
never run.

How: a fresh ``python`` subprocess per file with its working directory a temporary directory (examples that
write files write them there), the repository root first on ``PYTHONPATH``, ``MUJOCO_GL=egl`` unless the
caller set ``MUJOCO_GL`` already, and ``MPLBACKEND=Agg``. A traceback names the file and its Markdown line
numbers. The budget per file is ``ADARL_DOCS_TIMEOUT`` seconds (default 300).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
NO_RUN_MARKERS = ("no-run", "norun", "no_run", "skip")
PYTHON_LANGS = ("python", "py", "python3")
TIMEOUT_S = float(os.environ.get("ADARL_DOCS_TIMEOUT", "300"))

_OPEN = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^`]*?)[ \t]*$")


@dataclass(frozen=True)
class Block:
    line: int  # 1-based Markdown line of the first code line
    source: str
    info: str

    @property
    def runnable(self) -> bool:
        words = self.info.replace("{", " ").replace("}", " ").replace(",", " ").split()
        if not words or words[0].lower().lstrip(".") not in PYTHON_LANGS:
            return False
        return not any(w.lower() in NO_RUN_MARKERS for w in words[1:])


def extract_blocks(text: str) -> list[Block]:
    """All fenced code blocks of a Markdown text, in order (unterminated blocks run to the end)."""
    lines = text.splitlines()
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        m = _OPEN.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, info = m["indent"], m["fence"], m["info"]
        close = re.compile(rf"^[ \t]*{re.escape(fence[0])}{{{len(fence)},}}[ \t]*$")
        body: list[str] = []
        j = i + 1
        while j < len(lines) and not close.match(lines[j]):
            line = lines[j]
            body.append(line[len(indent) :] if line.startswith(indent) else line.lstrip(" \t"))
            j += 1
        blocks.append(Block(line=i + 2, source=textwrap.dedent("\n".join(body)) + "\n", info=info))
        i = j + 1
    return blocks


def doc_files() -> list[Path]:
    files = sorted((REPO / "docs").rglob("*.md")) if (REPO / "docs").is_dir() else []
    if (REPO / "README.md").is_file():
        files.append(REPO / "README.md")
    return files


# Runs the blocks in order in one namespace; each is compiled with its Markdown line offset so that a traceback
# points at the right line of the right file.
_RUNNER = r"""
import json, sys, traceback
blocks = json.load(open(sys.argv[1]))
ns = {"__name__": "__main__", "__file__": blocks[0]["file"] if blocks else "<docs>"}
for b in blocks:
    code = compile("\n" * (b["line"] - 1) + b["source"], b["file"], "exec")
    try:
        exec(code, ns)
    except SystemExit as err:
        if err.code not in (None, 0):
            print(f"DOCS-EXAMPLE-FAILED {b['file']}:{b['line']} (SystemExit {err.code!r})", file=sys.stderr)
            sys.exit(1)
    except BaseException:
        traceback.print_exc()
        print(f"DOCS-EXAMPLE-FAILED {b['file']}:{b['line']}", file=sys.stderr)
        sys.exit(1)
print(f"DOCS-EXAMPLES-OK {len(blocks)}")
"""


def run_blocks(label: str, blocks: list[Block], workdir: Path, timeout: float = TIMEOUT_S):
    payload = [{"file": label, "line": b.line, "source": b.source} for b in blocks]
    spec = workdir / "_docs_blocks.json"
    spec.write_text(json.dumps(payload))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    env.setdefault("MUJOCO_GL", "egl")
    env.setdefault("MPLBACKEND", "Agg")
    env.setdefault("PYTHONWARNINGS", "ignore")
    return subprocess.run(
        [sys.executable, "-c", _RUNNER, str(spec)],
        cwd=workdir,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _id(path: Path) -> str:
    return path.relative_to(REPO).as_posix()


@pytest.mark.parametrize("path", doc_files(), ids=_id)
def test_doc_examples_run(path: Path, tmp_path: Path):
    blocks = [b for b in extract_blocks(path.read_text(encoding="utf-8")) if b.runnable]
    if not blocks:
        pytest.skip(f"{_id(path)} has no runnable ```python blocks")
    try:
        proc = run_blocks(_id(path), blocks, tmp_path)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{_id(path)}: examples did not finish within {TIMEOUT_S:.0f} s (ADARL_DOCS_TIMEOUT)")
    if proc.returncode != 0:
        pytest.fail(
            f"{_id(path)}: an example failed (exit {proc.returncode})\n"
            f"--- stdout (tail) ---\n{proc.stdout[-3000:]}\n--- stderr (tail) ---\n{proc.stderr[-6000:]}",
            pytrace=False,
        )
    assert f"DOCS-EXAMPLES-OK {len(blocks)}" in proc.stdout


# Losses that stack their critics into an ensemble (TorchRL resamples the stacked factors uniformly)
ENSEMBLE_LOSSES = (
    "SACLoss",
    "DiscreteSACLoss",
    "TD3Loss",
    "TD3BCLoss",
    "REDQLoss",
    "CQLLoss",
    "CrossQLoss",
    "IQLLoss",
    "DiscreteIQLLoss",
    "TQCLoss",
)


def test_examples_with_low_rank_critic_ensembles_call_reinit_low_rank_ensemble():
    """docs/low-rank-linear.md says a critic ensemble over LowRankLinear layers needs reinit_low_rank_ensemble: every
    runnable example that builds one calls it (a user copies the examples)."""
    missing = []
    for path in doc_files():
        code = "\n".join(b.source for b in extract_blocks(path.read_text(encoding="utf-8")) if b.runnable)
        builds = [n for n in ENSEMBLE_LOSSES if re.search(rf"\b{n}\(", code)]
        if builds and re.search(r"\b(low_rank_mlp|LowRankLinear)\b", code) and "reinit_low_rank_ensemble(" not in code:
            missing.append(f"{_id(path)} ({', '.join(builds)})")
    assert not missing, f"examples build low-rank critic ensembles without reinit_low_rank_ensemble: {missing}"


# ---------------------------------------------------------------------------------------------------------
# the harness itself
# ---------------------------------------------------------------------------------------------------------

SAMPLE = """\
# Title

```python
x = 1
```

Some text.

```python no-run
raise RuntimeError("never executed")
```

```bash
exit 1
```

  ~~~py
  y = x + 1
  if y:
      z = y * 2
  ~~~

```pycon
>>> 1 + 1
```

````python {no-run}
nested = "```"
````

```Python
w = z + 1
```
"""


def test_extract_blocks_selects_and_orders():
    blocks = extract_blocks(SAMPLE)
    assert [b.info for b in blocks] == ["python", "python no-run", "bash", "py", "pycon", "python {no-run}", "Python"]
    run = [b for b in blocks if b.runnable]
    assert [b.source for b in run] == ["x = 1\n", "y = x + 1\nif y:\n    z = y * 2\n", "w = z + 1\n"]
    assert run[0].line == 4 and SAMPLE.splitlines()[run[0].line - 1] == "x = 1"
    assert SAMPLE.splitlines()[run[1].line - 1].strip() == "y = x + 1"


def test_runner_shares_one_namespace_and_reports_the_failing_line(tmp_path):
    blocks = [b for b in extract_blocks(SAMPLE) if b.runnable]
    ok = run_blocks("sample.md", blocks, tmp_path, timeout=60)
    assert ok.returncode == 0, ok.stderr
    assert "DOCS-EXAMPLES-OK 3" in ok.stdout
    bad = extract_blocks("```python\na = 1\n```\n\n```python\nb = a\n\nc = 1 / 0\n```\n")
    proc = run_blocks("bad.md", bad, tmp_path, timeout=60)
    assert proc.returncode == 1
    assert 'File "bad.md", line 8' in proc.stderr  # the Markdown line of `c = 1 / 0`
    assert "ZeroDivisionError" in proc.stderr
    assert "DOCS-EXAMPLE-FAILED bad.md:6" in proc.stderr


def test_runner_cwd_is_the_temporary_directory(tmp_path):
    blocks = extract_blocks("```python\nopen('made-by-example.txt', 'w').write('x')\n```\n")
    assert run_blocks("cwd.md", blocks, tmp_path, timeout=60).returncode == 0
    assert (tmp_path / "made-by-example.txt").is_file()
    assert not (REPO / "made-by-example.txt").exists()
