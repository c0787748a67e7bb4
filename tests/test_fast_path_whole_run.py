"""The fused SAC update against TorchRL's ``SACLoss`` step over a whole run, through rank events (issue 45).

Every reproduction run trained through the fused update (:class:`~adarl.fast.sac.FusedSACUpdate`, hand-written
backward); ``tests/test_fast_sac.py`` checks it against ``SACLoss`` one or two steps at a time. Here three copies of
one run train side by side for 300 updates through two rank events: TorchRL's path (``algorithm.fused: false``:
:class:`~adarl.runtime.update.LossStep`, ``SACLoss`` + for-loop Adam + ``SoftUpdate``) and the fused path with each
backward (``manual``, the default, and ``autograd``: :class:`~adarl.runtime.update.FusedStep`, fused Adam stepped by
``DirectAdamStep``, the ``UniformTensorSampler``). Each is built by the project's own builder
(:func:`~adarl.runtime.builders.sac.build_sac_components`) from ``recipes/hopper_adarl.yaml``, the reproduction's
recipe: Hopper's (64, 64) factorised actor and critics, ``rank.scope: both``, the energy rule with the projection
acceptance step, fixed alpha 0.2, lr 3e-3, warm-up + cosine LR restarted at each event, the warm start's refill; only
the budget is small (:data:`OVERRIDES`: an event every 120 updates, a 50-update warm-up over a 400-update cosine).
Each is driven as :meth:`OffPolicyTrainer._update
<adarl.runtime.trainers.off_policy.OffPolicyTrainer._update>` drives it, ``components.update(guard, update=n)`` then
``components.adapter.step()``, so an event runs the real wiring: the rule and the acceptance step on the recent
transitions, the in-place surgery, the Adam state of the resized factors dropped, the targets synced (or projected),
the LR schedules restarted, the update step re-bound, the warm start.

One fixed replay stream feeds all three: the same 1000 transitions in every buffer, sampled with the same generator
(its state is compared), and the warm start refills from the same fixed 500 (its source is the one component
replaced: a collector would step the env with policies that differ by rounding, and the chaos of collection could
hide or fake a difference). torch's RNG is set to the same state before each side's update, so SAC's
reparameterisation noise is the same (and each side must leave it in the same state: the same draws).

Compared after every update: the losses; every parameter (actor, critics, target critics, ``log_alpha``), and each
low-rank layer's product ``W1 W2``; every Adam state (``exp_avg``, ``exp_avg_sq``, ``step``; which parameters have
one); the learning rates; the sampling generator. At each event: the ranks chosen, the rule's candidates, the ranks
the acceptance step tried and its errors, how the targets were resized, the warm start's refill, the buffers.
Differences are ``||fused - torchrl|| / ||torchrl||`` per tensor; updates are numbered from 0 (``update=n``), so the
events come after updates 119 and 239.

Measured on this project's 2-core x86 machine (one thread; the largest over both fused backwards; "to the first
event" includes the event's update), against :data:`BOUNDS`:

=========== ================= ============= ============= ============= ============= =============
case        updates           losses        parameters    W1 W2         Adam exp_avg  exp_avg_sq
=========== ================= ============= ============= ============= ============= =============
float64 x2  all 300           1.7e-14       1.2e-13       1.8e-14       2.4e-13       7.8e-14
float32     to the 1st event  4.9e-7        2.1e-6        3.1e-7        5.3e-6        8.1e-7
float32     after it          1.6e-4        8.6e-4        1.1e-3        6.0e-2        7.9e-3
=========== ================= ============= ============= ============= ============= =============

(float64 x2: ``sync`` with alpha fixed, ``project`` with alpha learnt. Learning rates and Adam's step counts are
equal; every event chose the same ranks on all three paths: float32 actor.layer1 64 -> 55 -> 50 and critic.layer1
64 -> 53 -> 48, the first layers' candidates refused, the acceptance step's errors within 4e-8 of each other, the
nearest to its tolerance 8.7e-4 away. 300 updates of the three paths take ~12 s per case.)

float64 is the strict check: through both events the paths compute the same run to ~1e-13, so the fused update,
its hand-written backward, its Adam and Polyak steps and the event's wiring around it (state dropped, LR restarted,
targets synced or projected, the buffer refilled) are the same computation as TorchRL's. In float32, the
reproduction's dtype, they agree to rounding up to and through the first event; the event re-factorises each layer
from an SVD, which moves the factors' rounding difference by the inverse gaps of nearby singular values (to 2e-6;
the products stay at 3e-7). After it the float32 runs separate by chaos, not by a difference of the paths: a hidden
ReLU whose pre-activation lies within rounding of zero for one sample (float32 sync, update 250: 1.3e-7 in the fused
path, exactly 0.0 in TorchRL's) is on in one path and off in the other, and on a unit Adam has seen no gradient for
since the event dropped its state, Adam turns that one sample's gradient into a full-size step on one side only;
from there the runs drift apart (1e-6 to 1e-3 within 50 updates). Measured: with that sample replaced in both
batches, the two sides' gradients at update 250 agree to 2e-6; on the same parameters the two implementations'
gradients agree to <= 1.4e-5 at every update checked (236-261). With ``target_mode: project`` in float32 (not a case
here) the same happens from update 124 on, and the largest differences by update 300 are 9e-3 (factors), 2e-3
(products), 7e-2 (exp_avg), inside the chaos bounds. So the float32 bounds after the first event are loose, and
the float64 cases hold every update to rounding.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe
from adarl.runtime.guards import NonFiniteGuard
from adarl.runtime.update import FusedStep, LossStep

STEPS = 300
INTERVAL = 120  # rank events after the 120th and the 240th update (n = 119, 239)
WARM_START = 500
OVERRIDES = [
    "collector.total_frames=1400",  # 400 planned updates (frames after update_after = 1000): the cosine's length
    "collector.init_random_frames=1000",
    "replay.size=2000",
    f"rank.interval={INTERVAL}",
    "rank.num_threads=1",
    "lr_schedule.warmup_steps=50",
    f"replay.warm_start.frames={WARM_START}",
]
LOSSES = ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy")
BACKWARDS = ("manual", "autograd")

#: largest ``||fused - torchrl|| / ||torchrl||`` allowed per tensor kind: float64 at every update; float32 up to and
#: through the first event (rounding), then after it (chaos, see the module docstring). ``lr`` and ``step`` must be
#: equal, in every case.
BOUNDS = {
    "float64": {"loss": 1e-10, "param": 1e-10, "product": 1e-10, "exp_avg": 1e-10, "exp_avg_sq": 1e-10},
    "float32": {"loss": 1e-5, "param": 1e-4, "product": 1e-5, "exp_avg": 1e-3, "exp_avg_sq": 1e-4},
    "float32 chaos": {"loss": 1e-2, "param": 5e-2, "product": 2e-2, "exp_avg": 0.5, "exp_avg_sq": 0.2},
}
EXACT = ("lr", "step")


def _stream(n: int, seed: int, dtype: torch.dtype) -> TensorDict:
    """``n`` fixed transitions of Hopper's shapes (11 observations, 3 actions) from a seeded generator."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, 11, generator=g) * torch.linspace(0.2, 3.0, 11)
    action = torch.rand(n, 3, generator=g) * 2 - 1
    next_obs = obs + 0.1 * torch.randn(n, 11, generator=g)
    reward = next_obs[:, 5:6] - 1e-3 * action.pow(2).sum(-1, keepdim=True) + 1.0
    terminated = torch.rand(n, 1, generator=g) < 0.01
    nxt = {"observation": next_obs, "reward": reward, "terminated": terminated, "done": terminated.clone()}
    nxt["truncated"] = torch.zeros_like(terminated)
    data = TensorDict({"observation": obs, "action": action, "next": nxt}, [n])
    return data.apply(lambda t: t.to(dtype) if t.is_floating_point() else t)


class _FixedSource:
    """The warm start's source: a collector's ``reset``/``rollout`` contract on a fixed stream; ``policy`` is the
    loss's actor (the warm start checks that the policy it refills with runs the loss's own factors)."""

    def __init__(self, policy, data: TensorDict, per_batch: int = 250) -> None:
        self.policy, self.data, self.per_batch, self.pos = policy, data, per_batch, 0

    def reset(self) -> None:
        pass

    def rollout(self) -> TensorDict:
        out = self.data[self.pos : self.pos + self.per_batch].clone()
        self.pos += self.per_batch
        return out


class _Side:
    """One path's components from the recipe's builder, fed the fixed stream, stepped as the trainer steps them."""

    def __init__(self, backward: str | None, target_mode: str, dtype: torch.dtype, extra: list[str]) -> None:
        fused = ["algorithm.fused=true", f"algorithm.backward={backward}"] if backward else ["algorithm.fused=false"]
        recipe = load_recipe("hopper_adarl", [*OVERRIDES, f"rank.target_mode={target_mode}", *extra, *fused])
        default = torch.get_default_dtype()
        torch.set_default_dtype(dtype)  # networks, loss, targets and log_alpha in `dtype`
        try:
            self.c = build_sac_components(recipe)
        finally:
            torch.set_default_dtype(default)
        self.c.replay_buffer.extend(_stream(1000, 0, dtype))
        self.c.warm_start.source = _FixedSource(self.c.modules.actor, _stream(2 * WARM_START, 1, dtype))
        self.guard = NonFiniteGuard(self.c.guarded_parameters())
        self.name = backward or "torchrl"

    def step(self, n: int):
        """One update, then the adapter's count (maybe an event), as the trainer does; ``(losses, event)``."""
        losses = self.c.update(self.guard, update=n)
        return losses, self.c.adapter.step()

    def tensors(self, losses: dict) -> dict[str, torch.Tensor]:
        """Every tensor compared, by ``kind:name``: losses, parameters, factor products, Adam states, LRs."""
        loss = self.c.modules.loss
        live = {"log_alpha": loss.log_alpha}
        for attr in ("actor_network_params", "qvalue_network_params", "target_qvalue_network_params"):
            live.update({f"{attr}.{k}": v for k, v in getattr(loss, attr).flatten_keys(".").items()})
        names = {id(v): k for k, v in live.items()}
        out = {f"loss:{k}": losses[k].detach().reshape(()) for k in LOSSES}
        out.update({f"param:{k}": v.detach() for k, v in live.items()})
        for k, w1 in live.items():
            if k.endswith(".w1"):
                out[f"product:{k[:-3]}"] = torch.matmul(w1.detach(), live[k[:-3] + ".w2"].detach())
        for opt_name, opt in self.c.optimizers.items():
            out[f"lr:{opt_name}"] = torch.tensor(float(opt.param_groups[0]["lr"]), dtype=torch.float64)
            for p in opt.param_groups[0]["params"]:
                for key, value in (opt.state.get(p) or {}).items():
                    out[f"{key}:{names[id(p)]}"] = value.detach()
        return out


def _check_event(n: int, name: str, ev, ref, tol: float) -> None:
    """The same decision at an event: ranks, candidates, the ranks tried (errors within ``tol``), target handling."""
    assert ev.changed and ref.changed, f"the event after update {n} changed no rank: nothing of an event was tested"
    assert len(ev.layers) == len(ref.layers)
    for got, want in zip(ev.layers, ref.layers, strict=True):
        where = f"{name}, the event after update {n}, {want.name}"
        same = ("name", "old_rank", "new_rank", "candidate", "member_ranks", "target")
        assert [getattr(got, a) for a in same] == [getattr(want, a) for a in same], where
        assert [k for k, _ in got.tried or []] == [k for k, _ in want.tried or []], where
        for (_, e_got), (_, e_want) in zip(got.tried or [], want.tried or [], strict=True):
            assert abs(e_got - e_want) <= tol, f"{where}: acceptance errors {e_got} vs {e_want}"


def run_lockstep(target_mode: str, dtype: torch.dtype, extra: list[str] = ()) -> dict:
    """The three paths in lockstep for :data:`STEPS` updates, checked after every one; returns the measured drift
    ``{(backward, phase, kind): (largest difference, update, tensor)}`` and the events."""
    plain = _Side(None, target_mode, dtype, list(extra))
    fused = [_Side(b, target_mode, dtype, list(extra)) for b in BACKWARDS]
    assert isinstance(plain.c.update, LossStep)
    for side, backward in zip(fused, BACKWARDS, strict=True):
        assert isinstance(side.c.update, FusedStep) and side.c.update.fused.backward == backward
        none = dict.fromkeys(LOSSES, torch.zeros(()))
        start, ref = side.tensors(none), plain.tensors(none)
        assert start.keys() == ref.keys() and all(torch.equal(start[k], ref[k]) for k in ref), "builds differ"
    dname = "float64" if dtype == torch.float64 else "float32"
    drift: dict[tuple, tuple] = {}
    events = []
    torch.manual_seed(0)
    for n in range(STEPS):
        state = torch.get_rng_state()
        losses, ev_ref = plain.step(n)
        rng_after = torch.get_rng_state()
        ref = plain.tensors(losses)
        if ev_ref is not None:  # the LR schedules restarted: the next update runs at learning rate 0
            assert all(float(s.optimizer.param_groups[0]["lr"]) == 0.0 for s in plain.c.schedulers.values())
        first_event_done = len(plain.c.adapter.history) > (0 if ev_ref is None else 1)
        phase = dname if dname == "float64" or not first_event_done else "float32 chaos"
        for side in fused:
            torch.set_rng_state(state)
            losses, ev = side.step(n)
            assert torch.equal(torch.get_rng_state(), rng_after), f"update {n}: {side.name} drew other random numbers"
            got = side.tensors(losses)
            assert got.keys() == ref.keys(), f"update {n}, {side.name}: {sorted(got.keys() ^ ref.keys())}"
            for key, want in ref.items():
                kind = key.split(":", 1)[0]
                have = got[key]
                assert have.shape == want.shape, (
                    f"update {n}, {side.name}: {key} {tuple(have.shape)} vs {tuple(want.shape)}"
                )
                if kind in EXACT:
                    assert torch.equal(have.to(want.dtype), want), f"update {n}, {side.name}: {key} {have} vs {want}"
                    continue
                norm = float(want.norm())
                diff = float((have - want).norm())
                rel = diff / norm if norm > 0 else (0.0 if diff == 0 else float("inf"))
                slot = (side.name, "before" if not first_event_done else "after", kind)
                if rel > drift.get(slot, (-1.0,))[0]:
                    drift[slot] = (rel, n, key)
                assert rel <= BOUNDS[phase][kind], (
                    f"update {n} ({phase}), {side.name} vs torchrl: {key} differs by {rel:.3g} relative "
                    f"(bound {BOUNDS[phase][kind]:g})"
                )
            assert torch.equal(side.c.sampling_generator.get_state(), plain.c.sampling_generator.get_state())
            assert (ev is None) == (ev_ref is None), f"update {n}: an event on one side only"
            if ev is not None:
                _check_event(n, side.name, ev, ev_ref, {"float64": 1e-12, "float32": 1e-6}.get(phase, 1e-4))
                assert side.c.warm_start.records[-1] == plain.c.warm_start.records[-1]
                assert torch.equal(side.c.replay_buffer[:]["observation"], plain.c.replay_buffer[:]["observation"])
                events.append((n, side.name, ev, ev_ref))
    for side in fused:
        # the direct Adam kernels ran on every update but the first and, for an optimiser whose factors an event
        # resized (their state dropped), the first after that event: the fused path's fast step came back each time
        for name, adam in zip(side.c.optimizers, side.c.update.fused._adam_steps, strict=True):
            resized = [
                n
                for n, s, ev, _ in events
                if s == side.name and n < STEPS - 1 and any(r.changed and r.network == name for r in ev.layers)
            ]
            assert adam.fast_steps == STEPS - 1 - len(resized), (side.name, name, adam.fast_steps)
    return {"drift": drift, "events": events, "sides": [plain, *fused]}


CASES = {
    "float32-sync": (torch.float32, "sync", []),  # the reproduction's runs: float32, targets synced at a cut
    "float64-sync": (torch.float64, "sync", []),
    # the targets projected at a cut (the mechanism arm (a) of issue 45), and alpha learnt (its own Adam, no schedule)
    "float64-project-alpha": (torch.float64, "project", ["algorithm.fixed_alpha=false", "algorithm.init_alpha=1.0"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_fast_path_matches_torchrl_through_a_rank_event(case):
    dtype, target_mode, extra = CASES[case]
    result = run_lockstep(target_mode, dtype, extra)
    steps = sorted({n for n, *_ in result["events"]})
    assert steps == [INTERVAL - 1, 2 * INTERVAL - 1], steps
