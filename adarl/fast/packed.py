"""N independent SAC agents' updates as one batched program: the seeds of one arm stacked along a leading dimension.

Why: at (64, 64) a SAC update is bound by the number of operations, not by arithmetic (docs/performance.md): one
seed's update is ~700 small ATen calls. Stacking N seeds' parameters makes each of those calls one batched call for
all of them (``bmm`` over seeds, one Adam over a flat buffer), so the per-call overhead is paid once per update
instead of N times.

How: :class:`PackedSACUpdate` takes the N seeds' own :class:`~adarl.fast.sac.FusedSACUpdate` (each on its own
``SACLoss``, optimisers and LR schedules) and *packs* them: every parameter, target and Adam moment of the N seeds
moves into one flat buffer per optimiser group, and each seed's own tensors become views of its row(s) (``.data``
re-pointed, identities kept), so the seeds' collectors, evaluations and rank adapters see every update at no cost.
A low-rank layer whose rank differs between seeds is zero-padded to the largest: the padded columns of ``W1`` and
rows of ``W2`` get exactly zero gradient, zero Adam moments and hence stay exactly zero, so each seed computes a
rank-r layer's function (up to the order of fp sums). :meth:`PackedSACUpdate.unpack` gives each seed back
contiguous tensors of its own and writes the Adam state into its optimisers in ``torch.optim.Adam``'s format
(what a checkpoint saves and a rank adapter reads and pops); :meth:`PackedSACUpdate.pack` packs again.

What one seed gets is what its own ``FusedSACUpdate.step`` computes: the SAC v2 losses (manual backward), its own
per-optimiser-group gradient clipping, Adam with its own step counts (per parameter: a rank event resets only the
factors it changed) and its own learning rates (read from its optimisers, stepped by its own schedulers), and its
own Polyak update. The Gaussian noise of the two reparameterised samples is passed in per seed (drawn with each
seed's own generator state by the caller), so a packed seed can reproduce its solo run.

With ``algorithm.compile`` (the seeds' ``FusedSACUpdate.compile``) the step's computation and each optimiser group's
Adam are compiled (``torch.compile``) once per layout of padded shapes (the first pack, and a rank event that changes
the largest rank of a layer), each from a fresh code object so that dynamo never falls back to eager; a re-pack with
an unchanged layout (after a checkpoint) reuses them.

Mirrors: ``FusedSACUpdate.step`` (``backward="manual"``, fused Adam, ``polyak="factors"``) of each seed.
Equality: ``tests/test_packed.py::test_packed_seeds_match_their_solo_updates`` (parameters, targets, Adam states and
losses of every seed, with different ranks, popped Adam state and different learning rates per seed, within fp
tolerance; compiled, by a counting backend, and by inductor in
``test_packed_step_compiled_by_inductor_equals_eager``); what it does not implement is refused by name
(``tests/test_packed.py::test_packed_update_refuses_what_it_does_not_implement``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from adarl.core._surgery import _erase_loss_caches
from adarl.core.target_shift import TargetShiftSACLoss
from adarl.errors import AdaRLValueError
from adarl.fast.kernels import compile_fresh
from adarl.fast.manual_backward import ManualSACStep, _Net, backward, forward
from adarl.fast.sac import FusedSACUpdate

__all__ = ["PackedSACUpdate", "packing_refusal"]


def packing_refusal(update: FusedSACUpdate) -> str | None:
    """Why one seed's :class:`~adarl.fast.sac.FusedSACUpdate` cannot be packed (None: it can)."""
    if update.backward != "manual":
        return f"backward={update.backward!r} (packing runs the manual backward only)"
    if update.terms:
        return f"loss terms {sorted(update.terms)} (e.g. Parseval's)"
    if update.polyak != "factors":
        return f"polyak={update.polyak!r} (packing averages the factors, polyak='factors')"
    if isinstance(update.loss, TargetShiftSACLoss) and type(update.loss) is not TargetShiftSACLoss:
        return f"the TD-target shift of {type(update.loss).__name__}"
    for opt in update.optimizers:
        if not isinstance(opt, torch.optim.Adam):
            return f"the optimiser {type(opt).__name__} (packing runs Adam)"
        for g in opt.param_groups:
            bad = {
                k: g[k]
                for k, ok in (("weight_decay", 0), ("amsgrad", False), ("maximize", False))
                if g.get(k, ok) != ok
            }
            if bad:
                return f"Adam with {bad} (packing runs Adam with weight_decay=0, amsgrad=False, maximize=False)"
    return None


@dataclass
class _Slot:
    """One parameter of one optimiser group: its place in the group's flat buffer, per seed its own tensors."""

    key: str  # "actor:module.0.w1", "critic:module.0.bias", "log_alpha"
    shape: tuple[int, ...]  # the padded shape of one row block (critic: [2, ...] -> rows 2)
    offset: int
    numel: int
    lowrank: str | None = None  # "w1" (pad columns) | "w2" (pad rows) | None
    seed_params: list[torch.Tensor] = field(default_factory=list)
    seed_targets: list[torch.Tensor | None] = field(default_factory=list)


class _Group:
    """One optimiser group of every seed as flat buffers ``[N * rows, T]``: parameters, gradients, Adam moments,
    targets (critics), and per seed and parameter the Adam step count."""

    def __init__(self, opt_index: int, group_index: int, rows: int, slots: list[_Slot], n: int, dtype, device) -> None:
        self.opt_index, self.group_index = opt_index, group_index  # where in each seed's optimisers it lives
        self.rows, self.slots, self.n = rows, slots, n
        width = sum(s.numel for s in slots)
        self.param = torch.zeros(n * rows, width, dtype=dtype, device=device)
        self.exp_avg = torch.zeros_like(self.param)
        self.exp_avg_sq = torch.zeros_like(self.param)
        self.target = torch.zeros_like(self.param) if any(s.seed_targets[0] is not None for s in slots) else None
        self.steps = torch.zeros(n, len(slots), dtype=torch.float64, device=device)
        # for each element of one seed's rows, the index of its slot (per-parameter step counts -> per element)
        per_row = torch.cat([torch.full((s.numel,), j, dtype=torch.long) for j, s in enumerate(slots)])
        self.element_slot = per_row.repeat(rows).to(device)

    def view(self, buffer: torch.Tensor, slot: _Slot) -> torch.Tensor:
        """The stacked ``[N * rows, *shape]`` view of one slot in ``buffer``."""
        return buffer[:, slot.offset : slot.offset + slot.numel].view(self.n * self.rows, *slot.shape)


class PackedSACUpdate:
    """One SAC step for N seeds at once, each seed's :class:`~adarl.fast.sac.FusedSACUpdate` computed as its own.

    Args:
        updates: the seeds' fused updates, one per seed, each on its own loss, optimisers and schedulers (as
            ``build_sac_components`` makes them). They must share everything but their values and low-rank ranks:
            the layers, activations, sizes, ``gamma``, ``tau``, the critic loss, ``max_grad_norm``, the optimisers'
            groups and Adam's ``betas`` / ``eps`` (each seed keeps its own learning rates and schedules).

    The updates are packed at construction (:meth:`pack`). Call :meth:`step` with the seeds' batches and noise;
    :meth:`unpack` before anything that replaces a seed's tensors or reads its optimiser state (a rank event, a
    checkpoint), :meth:`pack` after it.
    """

    def __init__(self, updates: Sequence[FusedSACUpdate]) -> None:
        updates = list(updates)
        if not updates:
            raise AdaRLValueError("PackedSACUpdate needs at least one seed's FusedSACUpdate")
        for i, u in enumerate(updates):
            if not isinstance(u, FusedSACUpdate):
                raise AdaRLValueError(f"seed {i}: PackedSACUpdate packs FusedSACUpdate, got {type(u).__name__}")
            reason = packing_refusal(u)
            if reason is not None:
                raise AdaRLValueError(f"seed {i}: packed updates do not implement {reason}; train it unpacked")
        self.updates = updates
        self.n = len(updates)
        first = updates[0]
        self._check_alike(first, updates)
        self.u = first  # shared settings (gamma, tau, loss function, action box, scale mapping) are seed 0's
        self.gamma, self.tau, self.max_grad_norm = first.gamma, first.tau, first.max_grad_norm
        ext = first._param_extractor
        self._sp_bias, self._sp_min = float(ext.scale_mapping.bias), float(ext.scale_mapping.min_val)
        self._scale_lb = float(ext.scale_lb)
        # algorithm.compile (the seeds share it): the step's computation and each group's Adam are compiled once per
        # layout of padded shapes (the first pack and each rank event that changes it), kept for a re-pack with the
        # same layout (after a checkpoint) until the layout changes
        self.compile, self.compile_backend = bool(first.compile), first.compile_backend
        self._compiled: dict[tuple, tuple] = {}
        self.compilations = 0
        self.packed = False
        self.groups: list[_Group] = []
        self.pack()

    # ------------------------------------------------------------------ checks
    @staticmethod
    def _check_alike(first: FusedSACUpdate, updates: list[FusedSACUpdate]) -> None:
        def layout(u: FusedSACUpdate):
            def net(mlp):
                return [(k, type(s).__name__ if k == "act" else tuple(s)) for k, s in mlp.layers]

            return (
                net(u.actor_mlp),
                net(u.q_net),
                u.gamma,
                u.tau,
                u.max_grad_norm,
                u.loss_function,
                u.target_entropy,
                (u.min_log_alpha, u.max_log_alpha),
                u._affine,
                float(u._mid.sum()),
                float(u._half.sum()),
                [[(g.get("betas"), g.get("eps"), len(g["params"])) for g in o.param_groups] for o in u.optimizers],
                isinstance(u.loss, TargetShiftSACLoss),
                (bool(u.compile), u.compile_backend if u.compile else None),
            )

        ref = layout(first)
        for i, u in enumerate(updates[1:], start=1):
            got = layout(u)
            if got != ref:
                names = (
                    "actor layers",
                    "critic layers",
                    "gamma",
                    "tau",
                    "max_grad_norm",
                    "critic loss",
                    "target entropy",
                    "log-alpha bounds",
                    "action box",
                    "action box",
                    "action box",
                    "optimiser groups",
                    "target shift",
                    "algorithm.compile",
                )
                diff = [n for n, a, b in zip(names, ref, got, strict=True) if a != b]
                raise AdaRLValueError(
                    f"seed {i} differs from seed 0 in {sorted(set(diff))}: packed seeds must share everything but "
                    "their values, ranks and learning rates"
                )

    # ------------------------------------------------------------------ the seeds' tensors
    @staticmethod
    def _keyed(u: FusedSACUpdate) -> dict[str, tuple[torch.Tensor, torch.Tensor | None]]:
        """Every trained tensor of one seed by key, with its target (critics) or None."""
        out: dict[str, tuple[torch.Tensor, torch.Tensor | None]] = {
            f"actor:{k}": (p, None) for k, p in u.actor_params.items()
        }
        out.update({f"critic:{k}": (p, u.target_q_params[k]) for k, p in u.q_params.items()})
        out["log_alpha"] = (u.loss.log_alpha, None)
        return out

    @staticmethod
    def _lowrank_role(key: str) -> str | None:
        name = key.split(":", 1)[-1]
        if name.endswith(".w1"):
            return "w1"
        if name.endswith(".w2"):
            return "w2"
        return None

    def pack(self) -> None:
        """Move every seed's parameters, targets and Adam state into flat buffers; each seed's tensors become views.

        A low-rank layer is padded to the largest rank among the seeds (zeros, which stay zero)."""
        if self.packed:
            return
        first = self.updates[0]
        keyed = [self._keyed(u) for u in self.updates]
        dtype = first.loss.log_alpha.dtype
        self.device = self._one_device(keyed)
        # which optimiser group each key belongs to (seed 0's groups; the others have the same layout: checked)
        by_id = {id(t): k for k, (t, _) in keyed[0].items()}
        self.groups = []
        seen: set[str] = set()
        for oi, opt in enumerate(first.optimizers):
            for gi, group in enumerate(opt.param_groups):
                keys = [by_id.get(id(p)) for p in group["params"]]
                if None in keys:
                    raise AdaRLValueError(
                        f"optimiser {oi} group {gi} steps a tensor that is not the actor's, a critic's or log_alpha"
                    )
                nets = {k.split(":", 1)[0] for k in keys}
                if len(nets) != 1:
                    raise AdaRLValueError(
                        f"optimiser {oi} group {gi} mixes {sorted(nets)}: packing needs one per group"
                    )
                seen.update(keys)
                self.groups.append(self._make_group(oi, gi, keys, keyed, dtype, self.device))
        missing = sorted(set(keyed[0]) - seen)
        if missing and missing != ["log_alpha"]:
            raise AdaRLValueError(f"the optimisers do not step {missing}: packing steps every trained tensor")
        self._fixed_alpha = "log_alpha" in missing
        if self._fixed_alpha:
            self._alpha_view = torch.stack([u.loss.log_alpha.detach().reshape(()) for u in self.updates])
        self._bind()
        self.packed = True

    @staticmethod
    def _one_device(keyed: list[dict[str, tuple[torch.Tensor, torch.Tensor | None]]]) -> torch.device:
        """The device every seed's trained tensors and targets live on (the flat buffers are made there)."""
        where: dict[str, list[str]] = {}
        for i, kd in enumerate(keyed):
            for k, (p, t) in kd.items():
                for name, x in ((k, p), (f"{k} (target)", t)):
                    if x is not None:
                        where.setdefault(str(x.device), []).append(f"seed {i} {name}")
        if len(where) != 1:
            found = {d: names[:3] for d, names in sorted(where.items())}
            raise AdaRLValueError(
                f"packed seeds must live on one device: found {sorted(where)} (e.g. {found}); build every seed with "
                "the same recipe device"
            )
        return torch.device(next(iter(where)))

    def _make_group(self, oi, gi, keys, keyed, dtype, device) -> _Group:
        rows = 2 if keys[0].startswith("critic:") else 1
        slots: list[_Slot] = []
        offset = 0
        for k in keys:
            shapes = [tuple(kd[k][0].shape) for kd in keyed]
            role = self._lowrank_role(k)
            padded = list(shapes[0])
            for s in shapes[1:]:
                if len(s) != len(padded) or (role is None and s != tuple(padded)):
                    raise AdaRLValueError(f"{k}: shapes differ between seeds ({shapes[0]} vs {s})")
                padded = [max(a, b) for a, b in zip(padded, s, strict=True)]
            for kd, s in zip(keyed, shapes, strict=True):
                t = kd[k][1]
                if t is not None and tuple(t.shape) != s:
                    raise AdaRLValueError(f"{k}: the target's shape {tuple(t.shape)} differs from the online {s}")
            block = tuple(padded[1:]) if rows == 2 else tuple(padded)
            numel = math.prod(block) if block else 1
            slot = _Slot(k, block, offset, numel, role)
            slot.seed_params = [kd[k][0] for kd in keyed]
            slot.seed_targets = [kd[k][1] for kd in keyed]
            slots.append(slot)
            offset += numel
        group = _Group(oi, gi, rows, slots, self.n, dtype, device)
        for i, u in enumerate(self.updates):
            state = u.optimizers[oi].state
            for j, slot in enumerate(slots):
                p, t = slot.seed_params[i], slot.seed_targets[i]
                for buf, value in ((group.param, p), (group.target, t)):
                    if buf is not None and value is not None:
                        self._seed_block(group, buf, slot, i, tuple(p.shape)).copy_(value.detach())
                st = state.get(p)
                if st:
                    self._seed_block(group, group.exp_avg, slot, i, tuple(p.shape)).copy_(st["exp_avg"])
                    self._seed_block(group, group.exp_avg_sq, slot, i, tuple(p.shape)).copy_(st["exp_avg_sq"])
                    group.steps[i, j] = float(st["step"])
        return group

    @staticmethod
    def _seed_block(group: _Group, buffer: torch.Tensor, slot: _Slot, i: int, shape: tuple[int, ...]) -> torch.Tensor:
        """Seed ``i``'s tensor of full shape ``shape`` (critics ``[2, ...]``) as a view into ``buffer``."""
        v = group.view(buffer, slot)[i * group.rows : (i + 1) * group.rows]
        if group.rows == 1:
            v = v[0]
            return v[tuple(slice(0, d) for d in shape)] if shape else v
        return v[(slice(None), *(slice(0, d) for d in shape[1:]))]

    def _bind(self) -> None:
        """Point each seed's tensors at its views, and build the stacked views the step computes with."""
        self._stacked: dict[str, torch.Tensor] = {}
        self._stacked_target: dict[str, torch.Tensor] = {}
        for group in self.groups:
            for slot in group.slots:
                self._stacked[slot.key] = group.view(group.param, slot)
                if group.target is not None:
                    self._stacked_target[slot.key] = group.view(group.target, slot)
                for i in range(self.n):
                    p, t = slot.seed_params[i], slot.seed_targets[i]
                    p.data = self._seed_block(group, group.param, slot, i, tuple(p.shape))
                    if t is not None:
                        t.data = self._seed_block(group, group.target, slot, i, tuple(t.shape))
                    p.grad = None
        for u in self.updates:  # cached detached views of the old tensors (TorchRL's loss caches)
            _erase_caches(u.loss)
        actor = {k.split(":", 1)[1]: v for k, v in self._stacked.items() if k.startswith("actor:")}
        critic = {k.split(":", 1)[1]: v for k, v in self._stacked.items() if k.startswith("critic:")}
        target = {k.split(":", 1)[1]: v for k, v in self._stacked_target.items()}
        self.actor = _Net("actor", self.u.actor_mlp, actor)
        self.critic = _Net("critic", self.u.q_net, critic)
        self.target = _Net("target", self.u.q_net, target)
        self._compute, self._adam_kernels = self.compute, [_adam_kernel] * len(self.groups)
        if self.compile:
            self._compute, self._adam_kernels = self._compiled_for_layout()

    def _compiled_for_layout(self) -> tuple:
        """The compiled computation and per-group Adam kernels for the current padded shapes (built on first use:
        ``compile_fresh``, so each layout compiles once and dynamo never falls back to eager)."""
        key = (self.n, self._fixed_alpha, tuple((s.key, s.shape) for g in self.groups for s in g.slots))
        if key not in self._compiled:
            self.compilations += 1
            backend = self.compile_backend
            compute = compile_fresh(PackedSACUpdate.compute, self, "packed_sac_compute", backend)
            kernels = [compile_fresh(_adam_kernel, None, f"packed_adam_{i}", backend) for i in range(len(self.groups))]
            self._compiled = {key: (compute, kernels)}  # ranks only shrink: an older layout does not come back
        return self._compiled[key]

    def unpack(self) -> None:
        """Give each seed contiguous tensors of its own (the current values) and its Adam state in
        ``torch.optim.Adam``'s format (no state for a parameter never stepped since its last reset)."""
        if not self.packed:
            return
        for group in self.groups:
            for j, slot in enumerate(group.slots):
                for i, u in enumerate(self.updates):
                    p, t = slot.seed_params[i], slot.seed_targets[i]
                    shape = tuple(p.shape)
                    p.data = self._seed_block(group, group.param, slot, i, shape).clone()
                    if t is not None:
                        t.data = self._seed_block(group, group.target, slot, i, shape).clone()
                    state = u.optimizers[group.opt_index].state
                    step = float(group.steps[i, j])
                    if step == 0:
                        state.pop(p, None)
                        continue
                    old = state.get(p) or {}
                    step_dtype = old["step"].dtype if "step" in old else torch.float32
                    state[p] = {
                        "step": torch.tensor(step, dtype=step_dtype),
                        "exp_avg": self._seed_block(group, group.exp_avg, slot, i, shape).clone(),
                        "exp_avg_sq": self._seed_block(group, group.exp_avg_sq, slot, i, shape).clone(),
                    }
        for u in self.updates:
            _erase_caches(u.loss)
        self.groups = []
        self.packed = False

    # ------------------------------------------------------------------ the maths (ManualSACStep with seeds)
    # The TanhNormal sample, its backward and the critic loss's gradient are element-wise: the manual step's own code
    # (it reads ``self.u`` and the scale mapping's constants, which this class holds under the same names) runs on
    # ``[N, ...]`` tensors as it does on ``[...]`` ones.
    _sample = ManualSACStep._sample
    _sample_backward = ManualSACStep._sample_backward
    _distance_grad = ManualSACStep._distance_grad

    def compute(self, obs, action, reward, next_obs, terminated, noise_next, noise_now):
        """Losses ``[N]`` and gradients by key (stacked) of every seed; tensors are ``[N, B, ...]``."""
        u, n = self.u, self.n
        log_alpha = self._log_alpha()
        alpha = log_alpha.exp()  # [N]
        b = obs.shape[-2]
        nxt, now = slice(0, b), slice(b, 2 * b)
        ds = obs.shape[-1]

        actor = self.actor.prepare(2 * b, b, b)
        a_out, a_saved = forward(actor, torch.cat([next_obs, obs], 1))
        act_all, logp_all, s_saved = self._sample(a_out, torch.cat([noise_next, noise_now], 1))
        next_action, new_action = act_all[:, nxt], act_all[:, now]
        next_logp, logp = logp_all[:, nxt], logp_all[:, now]

        def per_critic(x: torch.Tensor) -> torch.Tensor:  # [N, R, d] -> [2N, R, d], seed-major
            return x.unsqueeze(1).expand(n, 2, *x.shape[1:]).reshape(2 * n, *x.shape[1:])

        target_q = self.target.prepare(b, 0, 0)
        q_next, _ = forward(target_q, per_critic(torch.cat([next_obs, next_action], -1)))  # [2N, B, 1]
        q_next = q_next.view(n, 2, b, 1)
        next_value = (q_next - alpha.view(n, 1, 1, 1) * next_logp.view(n, 1, b, 1)).min(1)[0]  # [N, B, 1]
        target = (reward + self.gamma * (~terminated).to(reward.dtype) * next_value).squeeze(-1)  # [N, B]

        critic = self.critic.prepare(2 * b, b, 2 * b)
        x_all = torch.cat([torch.cat([obs, action], -1), torch.cat([obs, new_action], -1)], 1)  # [N, 2B, d]
        q_all, c_saved = forward(critic, per_critic(x_all))
        q_all = q_all.view(n, 2, 2 * b)
        pred, q_new = q_all[..., nxt], q_all[..., now]
        tgt = target.unsqueeze(1).expand_as(pred)
        loss_q = u._distance(pred, tgt).sum(1).mean(-1)  # [N]
        q_min, q_idx = q_new.min(1)
        loss_actor = (alpha.view(n, 1) * logp - q_min).mean(-1)
        loss_alpha = (-log_alpha.view(n, 1) * (logp + u.target_entropy)).mean(-1)

        d_q = torch.zeros_like(q_new).scatter_(1, q_idx.unsqueeze(1), -1.0 / b)
        d_pred = self._distance_grad(pred, tgt, 1.0 / b)
        d_all = torch.cat([d_pred, d_q], -1).reshape(2 * n, 2 * b, 1)
        grads: dict[str, torch.Tensor] = {}
        d_new_action = backward(
            grads, critic, c_saved, d_all, rows=slice(None), grad_rows=nxt, input_rows=now, input_cols=slice(ds, None)
        )
        d_new_action = d_new_action.view(n, 2, b, -1).sum(1)  # the two critics share their input
        d_logp = (alpha / b).view(n, 1, 1)
        d_out = self._sample_backward(s_saved, now, d_new_action, d_logp)  # d_logp [N, 1, 1]: per seed
        backward(grads, actor, a_saved, d_out, rows=now, grad_rows=slice(None))
        grads["log_alpha"] = -(logp + u.target_entropy).mean(-1)
        return loss_actor, loss_q, loss_alpha, alpha, -logp.mean(-1), grads

    def _log_alpha(self) -> torch.Tensor:
        if self._fixed_alpha:
            return self._alpha_view
        return self._stacked["log_alpha"].reshape(self.n)

    # ------------------------------------------------------------------ one step
    @torch.no_grad()
    def step(
        self,
        batches: Sequence[Sequence[torch.Tensor]],
        noises: Sequence[tuple[torch.Tensor, torch.Tensor]],
    ) -> dict[str, torch.Tensor]:
        """One update of every seed: ``batches[i]`` is seed ``i``'s five tensors (as
        :meth:`FusedSACUpdate.batch_tensors`), ``noises[i]`` its ``(noise_next, noise_now)`` (as
        :meth:`FusedSACUpdate.draw_noise`). Returns the losses and metrics as ``[N]`` tensors by name."""
        if not self.packed:
            raise AdaRLValueError("the packed update is unpacked: call pack() after the rank event or checkpoint")
        if len(batches) != self.n or len(noises) != self.n:
            raise AdaRLValueError(
                f"one batch and one noise pair per seed: {self.n} seeds, got {len(batches)}, {len(noises)}"
            )
        u = self.u
        if not self._fixed_alpha and (u.min_log_alpha is not None or u.max_log_alpha is not None):
            self._stacked["log_alpha"].clamp_(u.min_log_alpha, u.max_log_alpha)
        obs, action, reward, next_obs, terminated = (torch.stack(ts) for ts in zip(*batches, strict=True))
        noise_next = torch.stack([nz[0] for nz in noises])
        noise_now = torch.stack([nz[1] for nz in noises])
        shift = None
        if isinstance(u.loss, TargetShiftSACLoss):
            shift = torch.stack([v.loss.target_shift().detach().reshape(()) for v in self.updates])
            reward = reward - shift.view(self.n, 1, 1)
        loss_actor, loss_q, loss_alpha, alpha, entropy, grads = self._compute(
            obs, action, reward, next_obs, terminated.bool(), noise_next, noise_now
        )
        for group, kernel in zip(self.groups, self._adam_kernels, strict=True):
            self._adam(group, grads, kernel)
        with warnings.catch_warnings():  # the seeds' Adam steps are this update's, not optimizer.step()
            warnings.filterwarnings("ignore", message=r"Seems like `optimizer.step\(\)` has been overridden")
            warnings.filterwarnings("ignore", message=r"Detected call of `lr_scheduler.step\(\)` before")
            for v in self.updates:
                for sched in v.schedulers:
                    sched.step()
        for group in self.groups:
            if group.target is not None:
                group.target.lerp_(group.param, self.tau)
        out = {"loss_actor": loss_actor, "loss_qvalue": loss_q, "loss_alpha": loss_alpha, "alpha": alpha}
        out["entropy"] = entropy
        if shift is not None:
            out["target_shift"] = shift
        return out

    @torch.no_grad()
    def params_finite(self) -> torch.Tensor:
        """Per seed ``[N]``, whether every trained tensor is finite: one pass over the flat buffers (a seed's
        :class:`~adarl.runtime.guards.NonFiniteGuard` then names the tensor only where one is not)."""
        ok = torch.ones(self.n, dtype=torch.bool, device=self.device)
        for group in self.groups:
            ok &= torch.isfinite(group.param.view(self.n, -1)).all(1)
        return ok

    def _adam(self, group: _Group, grads: dict[str, torch.Tensor], kernel) -> None:
        """Clip (per seed, the group's norm) and take one Adam step for every seed, each at its own rates, with
        ``kernel`` (:func:`_adam_kernel`, or its compiled form)."""
        n = self.n
        rows = group.rows
        grad = torch.cat([grads[s.key].reshape(n * rows, -1) for s in group.slots], 1).view(n, -1)
        opt_index, group_index = group.opt_index, group.group_index
        ref = self.updates[0].optimizers[opt_index].param_groups[group_index]
        beta1, beta2 = ref["betas"]
        lr = torch.tensor(
            [float(v.optimizers[opt_index].param_groups[group_index]["lr"]) for v in self.updates],
            dtype=torch.float64,
            device=group.steps.device,
        ).view(n, 1)
        group.steps.add_(1)
        bc1 = 1 - beta1**group.steps  # [N, slots]
        bc2_sqrt = (1 - beta2**group.steps).sqrt()
        step_size = (lr / bc1).to(grad.dtype).index_select(1, group.element_slot)
        bc2_sqrt = bc2_sqrt.to(grad.dtype).index_select(1, group.element_slot)
        clip = None
        if self.max_grad_norm is not None:  # per seed, the group's norm
            norm = torch.linalg.vector_norm(grad, dim=1, keepdim=True)
            clip = (self.max_grad_norm / (norm + 1e-6)).clamp_(max=1.0)
        kernel(
            grad,
            group.param.view(n, -1),
            group.exp_avg.view(n, -1),
            group.exp_avg_sq.view(n, -1),
            step_size,
            bc2_sqrt,
            float(beta1),
            float(beta2),
            float(ref["eps"]),
            clip,
        )


def _adam_kernel(grad, param, exp_avg, exp_avg_sq, step_size, bc2_sqrt, beta1, beta2, eps, clip) -> None:
    """Adam's moments and step for every seed, in place on the ``[N, T]`` buffers, the gradient scaled by ``clip``
    (``[N, 1]``, None: not clipped) first: the part of :meth:`PackedSACUpdate._adam` that ``algorithm.compile``
    fuses (``step_size`` and ``bc2_sqrt`` are per element, from each seed's learning rate and step counts). The
    clipping factor is computed outside: inductor (torch 2.13) fails with ``KeyError: 'buf5'`` when the norm's
    reduction feeds both moments in one kernel."""
    if clip is not None:
        grad = grad * clip
    exp_avg.lerp_(grad, 1 - beta1)
    exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
    denom = (exp_avg_sq.sqrt() / bc2_sqrt).add_(eps)
    param.sub_(step_size * exp_avg / denom)


def _erase_caches(loss) -> None:

    _erase_loss_caches(loss)
