"""Two run folders made from the same recipe and seed at two commits: the same run bit for bit? Compares eval.csv byte
for byte and every entry of the last checkpoint (tensors with ``torch.equal``, the rest with ``==``) but the
wall-clock counter; prints each difference and exits 1 on any. Issue 45's amendment for Humanoid's row
(docs/reproduction.md) runs it on a short ``baselines/humanoid_sparse`` run at 6f73355 and at the commit
humanoid_commit names (same_layer_check.sh).

    python docs/reports/issue45/same_layer_check.py RUN_A RUN_B
"""

import sys
from pathlib import Path

import torch

WALL_CLOCK = "/state/counters/wall_time_s"  # the one entry two identical runs differ in


def leaves(obj, path=""):
    if isinstance(obj, dict):
        for key, value in obj.items():
            yield from leaves(value, f"{path}/{key}")
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            yield from leaves(value, f"{path}/{i}")
    else:
        yield path, obj


def last_checkpoint(run: Path) -> dict:
    ckpts = sorted((run / "checkpoints").glob("ckpt-*.pt"))
    if not ckpts:
        sys.exit(f"{run}: no checkpoints/ckpt-*.pt")
    return dict(leaves(torch.load(ckpts[-1], map_location="cpu", weights_only=True))), ckpts[-1].name


def main() -> int:
    a, b = (Path(p) for p in sys.argv[1:3])
    diffs = []
    if (a / "eval.csv").read_bytes() != (b / "eval.csv").read_bytes():
        diffs.append("eval.csv")
    (ca, na), (cb, nb) = last_checkpoint(a), last_checkpoint(b)
    if na != nb:
        diffs.append(f"last checkpoint {na} vs {nb}")
    tensors = 0
    for key in sorted((ca.keys() | cb.keys()) - {WALL_CLOCK}):
        x, y = ca.get(key), cb.get(key)
        if isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor):
            tensors += 1
            same = x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y)
        else:
            same = x == y
        if not same:
            diffs.append(key)
    rows = len((a / "eval.csv").read_text().splitlines()) - 1
    print(f"{a} vs {b}: eval.csv ({rows} evaluations) and {na} ({tensors} tensors, {len(ca)} entries) compared")
    for d in diffs:
        print(f"  differs: {d}")
    print("the same bit for bit" if not diffs else f"{len(diffs)} differences")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
