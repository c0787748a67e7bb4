"""What a checkpoint holds besides networks and optimisers: the global RNGs, and the collector's half of the live
episode (its counters and carrier), so that a resumed run continues the very episode it was in.

The env's half (simulator, gymnasium counters and RNG) is :mod:`adarl.envs.state`. Everything is plain tensors,
numbers and strings, so it loads with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import json
import random

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector

__all__ = ["seed_everything", "rng_state", "set_rng_state", "collector_state_dict", "load_collector_state_dict"]


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (CPU determinism is what the exact-resume guarantee relies on)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_state() -> dict:
    """The global torch, NumPy and Python RNG states, as plain tensors, numbers and strings."""
    np_state = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": {
            "key": np_state[0],
            "state": torch.from_numpy(np_state[1].astype(np.int64)),
            "pos": int(np_state[2]),
            "has_gauss": int(np_state[3]),
            "cached_gaussian": float(np_state[4]),
        },
        "python": json.dumps(random.getstate()),
        # a run on a GPU draws its update noise there (FusedSACUpdate.draw_noise): its generators resume with it
        **({"cuda": torch.cuda.get_rng_state_all()} if torch.cuda.is_initialized() else {}),
    }


def set_rng_state(state: dict) -> None:
    """Put back what :func:`rng_state` saved."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state(
        (n["key"], n["state"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached_gaussian"])
    )
    py = json.loads(state["python"])
    random.setstate((py[0], tuple(py[1]), py[2]))
    if "cuda" in state:
        torch.cuda.set_rng_state_all(state["cuda"])


def collector_state_dict(collector) -> dict:
    """The collector's counters, trajectory-id pool and carrier (the TorchRL half of the live episode).

    TorchRL's single-process ``Collector`` keeps its carrier in private fields that its own ``state_dict()`` leaves
    out; any other collector (:class:`~adarl.fast.collector.LeanCollector`) saves itself with ``state_dict()``."""
    if not isinstance(collector, Collector):
        return collector.state_dict()
    sd = collector.state_dict()
    return {
        "frames": int(sd.get("frames", collector._frames)),
        "iter": int(sd.get("iter", getattr(collector, "_iter", 0))),
        "traj_pool": sd.get("traj_pool"),
        "carrier": collector._carrier.to_dict(),
        "carrier_batch_size": list(collector._carrier.batch_size),
    }


def load_collector_state_dict(collector, state: dict, *, carrier: bool = True) -> None:
    """Put back what :func:`collector_state_dict` saved (``carrier=False``: the episode is not continued, e.g. when
    the env state could not be restored)."""
    if not isinstance(collector, Collector):
        collector.load_state_dict(state, carrier=carrier)
        return
    collector._frames = int(state["frames"])
    collector._iter = int(state["iter"])
    if state.get("traj_pool") is not None and getattr(collector, "track_traj_ids", False):
        collector._traj_pool.load_state_dict(state["traj_pool"])
    if carrier:
        old = collector._carrier
        new = TensorDict(state["carrier"], batch_size=state["carrier_batch_size"], device=old.device)
        if getattr(collector, "_carrier_has_no_device", False):
            new.clear_device_()
        collector._carrier = new
