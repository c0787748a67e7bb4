"""Packed seeds (adarl.fast.packed): N seeds' SAC updates as one batched program, each seed computed as its own."""

from __future__ import annotations

import copy

import pytest
import torch
from _helpers import BUILT

from adarl.core._surgery import resize_to_ranks
from adarl.errors import AdaRLValueError
from adarl.fast.packed import PackedSACUpdate, _adam_kernel
from adarl.runtime.builders.sac import build_sac_components
from adarl.runtime.config import load_recipe
from adarl.runtime.update import FusedStep

SEEDS = 3


def _fused(seed: int, *overrides: str):
    """A seed's quickstart components on the fused path, 300 frames in its buffer: its FusedSACUpdate and sampler."""
    recipe = load_recipe(
        "quickstart",
        [*BUILT, "algorithm.fused=true", "algorithm.max_grad_norm=0.5", f"seed={seed}", *overrides],
    )
    c = build_sac_components(recipe)
    torch.manual_seed(seed)
    c.replay_buffer.extend(c.env.rollout(300, break_when_any_done=False).reshape(-1))
    assert isinstance(c.update, FusedStep)
    with torch.no_grad():
        c.modules.loss.log_alpha.fill_(-0.5 - 0.1 * seed)
        for p in c.modules.loss.target_qvalue_network_params.flatten_keys().values():
            p.add_(0.01 * torch.randn_like(p))
    return c


@pytest.fixture(scope="module")
def seeds():
    return [_fused(s) for s in range(SEEDS)]


def _batches(cs, steps: int, seed: int = 11):
    """Per step, per seed: the five tensors and the noise pair (drawn per seed from its own generator state)."""
    torch.manual_seed(seed)
    batches = [[tuple(t.clone() for t in c.update.sampler()) for c in cs] for _ in range(steps)]
    noises = []
    for k in range(steps):
        row = []
        for i, c in enumerate(cs):
            torch.manual_seed(1000 * k + i)
            row.append(c.update.fused.draw_noise(batches[k][i][0], batches[k][i][1]))
        noises.append(row)
    return batches, noises


def _state(update):
    """Every value a seed carries from one step to the next: parameters, targets, log_alpha, Adam state, LRs."""
    loss = update.loss
    out = {f"p:{k}": v.detach().clone() for k, v in loss.actor_network_params.flatten_keys().items()}
    out |= {f"q:{k}": v.detach().clone() for k, v in loss.qvalue_network_params.flatten_keys().items()}
    out |= {f"t:{k}": v.detach().clone() for k, v in loss.target_qvalue_network_params.flatten_keys().items()}
    out["log_alpha"] = loss.log_alpha.detach().clone()
    for oi, opt in enumerate(update.optimizers):
        for gi, group in enumerate(opt.param_groups):
            out[f"lr:{oi}.{gi}"] = torch.tensor(group["lr"], dtype=torch.float64)
            for pi, p in enumerate(group["params"]):
                st = opt.state.get(p)
                if st:
                    out[f"adam:{oi}.{gi}.{pi}.step"] = torch.as_tensor(float(st["step"]))
                    out[f"adam:{oi}.{gi}.{pi}.m"] = st["exp_avg"].clone()
                    out[f"adam:{oi}.{gi}.{pi}.v"] = st["exp_avg_sq"].clone()
    return out


def _solo(update, batches, noises, i):
    losses = []
    for k in range(len(batches)):
        noise = noises[k][i]
        update.draw_noise = lambda obs, action, noise=noise: noise  # the same noise the packed seed gets
        out = update.step(*batches[k][i])
        losses.append(torch.stack([out[n] for n in ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy")]))
    del update.draw_noise
    return losses


def _truncate(c, layer_ranks: dict[str, int]) -> None:
    """What a rank event does to a seed: layers re-factorised to new ranks, their Adam state dropped."""
    resize_to_ranks(c.modules.loss, layer_ranks, list(c.optimizers.values()))


def _copies(cs):
    return [copy.deepcopy(c.update.fused) for c in cs]


def _counting_backend(graphs: list):
    """``aot_eager`` that records each graph it is handed: every compilation, counted."""
    from torch._dynamo.backends.registry import lookup_backend

    def backend(gm, example_inputs):
        graphs.append(gm)
        return lookup_backend("aot_eager")(gm, example_inputs)

    return backend


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
def test_packed_seeds_match_their_solo_updates(seeds, compiled):
    """Three seeds, each with its own values, a rank the others do not share, its own Adam history (state popped
    for the truncated factors) and learning rate, through a rank event between two stretches of updates: the packed
    update gives every seed the parameters, targets, Adam state, learning rates and losses of its solo updates.

    ``compiled`` (``algorithm.compile``, traced by dynamo with a counting ``aot_eager`` backend): the same against
    the eager solo updates, one compilation per layout of padded shapes (the first pack and the rank event), none
    for a re-pack with an unchanged layout (a checkpoint's), never dynamo's fall-back to eager."""
    cs = [copy.deepcopy(c) for c in seeds]
    for c in cs:  # an Adam history of its own, before anything differs
        for _ in range(2):
            c.update()
    ranks = dict(cs[0].adapter.ranks)
    paths = sorted(ranks)
    _truncate(cs[1], {paths[0]: ranks[paths[0]] - 9, paths[-1]: ranks[paths[-1]] - 5})  # seed 1: two layers narrower
    for group in cs[2].optimizers["critic"].param_groups:  # seed 2: its own critic learning rate
        group["lr"] *= 0.5
        group["initial_lr"] = group.get("initial_lr", group["lr"]) * 0.5
    for sched in cs[2].schedulers.values():
        sched.base_lrs = [lr * 0.5 for lr in sched.base_lrs]

    solo = _copies(cs)
    packed_seeds = _copies(cs)
    first, second = _batches(cs, 4, seed=1), _batches(cs, 3, seed=2)

    solo_losses = [_solo(u, *first, i) for i, u in enumerate(solo)]
    graphs: list = []
    if compiled:
        backend = _counting_backend(graphs)  # one for every seed, as their equal recipes name one
        for u in packed_seeds:
            u.compile, u.compile_backend = True, backend
    packed = PackedSACUpdate(packed_seeds)
    packed_losses = [packed.step(b, n) for b, n in zip(first[0][:2], first[1][:2], strict=True)]
    per_layout = 1 + len(packed.groups)  # the computation and each group's Adam: one graph each, no break
    assert len(graphs) == (per_layout if compiled else 0) and packed.compilations == int(compiled)
    packed.unpack()  # a checkpoint between updates: the same layout packs again without compiling
    packed.pack()
    packed_losses += [packed.step(b, n) for b, n in zip(first[0][2:], first[1][2:], strict=True)]
    assert len(graphs) == (per_layout if compiled else 0) and packed.compilations == int(compiled)
    # the padding of seed 1's narrower layers stays exactly zero
    for group in packed.groups:
        for slot in group.slots:
            if slot.lowrank is None:
                continue
            p = slot.seed_params[1]
            stacked = group.view(group.param, slot)
            rows = stacked[group.rows : 2 * group.rows]
            real = p.shape[-1] if slot.lowrank == "w1" else p.shape[-2]
            pad = rows[..., real:] if slot.lowrank == "w1" else rows[..., real:, :]
            assert pad.numel() == 0 or torch.equal(pad, torch.zeros_like(pad)), slot.key
    packed.unpack()

    # a rank event narrowing one layer of every seed by a different amount (its Adam state dropped), so that the
    # padded layout changes too, then more updates
    for c_list in (solo, packed_seeds):
        for i, cut in enumerate((7, 3, 5)):
            resize_to_ranks(c_list[i].loss, {paths[1]: ranks[paths[1]] - cut}, c_list[i].optimizers)
    solo_losses2 = [_solo(u, *second, i) for i, u in enumerate(solo)]
    packed.pack()
    packed_losses2 = [packed.step(b, n) for b, n in zip(*second, strict=True)]
    packed.unpack()
    assert len(graphs) == (2 * per_layout if compiled else 0) and packed.compilations == 2 * int(compiled)

    for i in range(SEEDS):
        got, want = _state(packed_seeds[i]), _state(solo[i])
        assert sorted(got) == sorted(want), i
        for k in want:
            torch.testing.assert_close(got[k], want[k], rtol=1e-4, atol=1e-6, msg=f"seed {i} {k}")
        for stretch_p, stretch_s in ((packed_losses, solo_losses[i]), (packed_losses2, solo_losses2[i])):
            for out, ref in zip(stretch_p, stretch_s, strict=True):
                names = ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy")
                torch.testing.assert_close(torch.stack([out[n][i] for n in names]), ref, rtol=1e-4, atol=1e-6)
    # the seeds did differ and did move: the comparison is not between copies of one thing
    assert not torch.equal(_state(packed_seeds[0])["log_alpha"], _state(packed_seeds[1])["log_alpha"])
    assert not torch.equal(_state(packed_seeds[2])["log_alpha"], _state(cs[2].update.fused)["log_alpha"])
    assert cs[1].adapter.ranks[paths[0]] == ranks[paths[0]] - 9 != cs[0].adapter.ranks[paths[0]]


def test_packed_step_compiled_by_inductor_equals_eager(seeds):
    """What ``algorithm.compile: true`` runs in a pack: the packed computation and each group's Adam kernel compiled
    by inductor (fused C++ kernels) give the eager ones' losses, gradients and Adam updates within fp tolerance."""
    us = _copies(seeds[:2])
    for u in us:
        u.compile, u.compile_backend = True, "inductor"
    packed = PackedSACUpdate(us)
    batches, noises = _batches(seeds[:2], 1, seed=5)
    obs, action, reward, next_obs, terminated = (torch.stack(ts) for ts in zip(*batches[0], strict=True))
    args = (obs, action, reward, next_obs, terminated.bool(), *(torch.stack(nz) for nz in zip(*noises[0], strict=True)))
    with torch.no_grad():
        *out_c, grads_c = packed._compute(*args)
        *out_e, grads_e = packed.compute(*args)
    assert sorted(grads_c) == sorted(grads_e) and packed.compilations == 1
    for a, b in zip(out_c + [grads_c[k] for k in sorted(grads_c)], out_e + [grads_e[k] for k in sorted(grads_e)]):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)
    gen = torch.Generator().manual_seed(0)
    for group, kernel in zip(packed.groups, packed._adam_kernels, strict=True):
        flat = group.param.view(2, -1)
        grad = torch.randn(flat.shape, generator=gen)
        state = [flat.clone(), torch.randn(flat.shape, generator=gen), torch.rand(flat.shape, generator=gen)]
        sizes = (torch.full_like(flat, 3e-4), torch.full_like(flat, 0.2))
        compiled, eager = [t.clone() for t in state], [t.clone() for t in state]
        clip = torch.tensor([[0.5], [1.0]])
        kernel(grad, *compiled, *sizes, 0.9, 0.999, 1e-8, clip)
        _adam_kernel(grad, *eager, *sizes, 0.9, 0.999, 1e-8, clip)
        for a, b, before in zip(compiled, eager, state, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
            assert not torch.equal(a, before)  # the kernel did update in place


def test_packed_seed_tensors_are_live_views(seeds):
    """While packed, a seed's own parameters are views of the stacked buffers: its collector acts with the
    parameters of the latest update, with no copy; unpacked, each tensor owns its storage again."""
    us = _copies(seeds[:2])
    packed = PackedSACUpdate(us)
    p = next(iter(us[1].actor_params.values()))
    before = p.detach().clone()
    batches, noises = _batches(seeds[:2], 2)
    for b, n in zip(batches, noises, strict=True):  # the first step's warm-up learning rate is 0
        packed.step(b, n)
    assert not torch.equal(p.detach(), before)  # the seed's own tensor moved with the packed step
    base = packed.groups[0].param
    assert p.untyped_storage().data_ptr() == base.untyped_storage().data_ptr()
    packed.unpack()
    assert p.untyped_storage().data_ptr() != base.untyped_storage().data_ptr()
    assert p.is_contiguous()


def test_packed_update_refuses_what_it_does_not_implement(seeds):
    u = copy.deepcopy(seeds[0].update.fused)
    u.backward = "autograd"
    with pytest.raises(AdaRLValueError, match=r"seed 0: .*backward='autograd'"):
        PackedSACUpdate([u])
    a, b = _copies(seeds[:2])
    b.gamma = 0.5
    with pytest.raises(AdaRLValueError, match=r"seed 1 differs from seed 0 in \['gamma'\]"):
        PackedSACUpdate([a, b])
    with pytest.raises(AdaRLValueError, match="at least one"):
        PackedSACUpdate([])
    a, b = _copies(seeds[:2])
    packed = PackedSACUpdate([a, b])
    batches, noises = _batches(seeds[:2], 1)
    with pytest.raises(AdaRLValueError, match="one batch and one noise pair per seed: 2 seeds, got 1"):
        packed.step(batches[0][:1], noises[0][:1])
    packed.unpack()
    with pytest.raises(AdaRLValueError, match="unpacked: call pack"):
        packed.step(batches[0], noises[0])


def test_packed_update_lives_on_its_seeds_device(seeds, monkeypatch):
    """The flat buffers, step counts and per-seed rates are made on the seeds' device (a GPU pack computes there),
    and seeds on different devices are refused by name before anything is copied."""
    a, b = _copies(seeds[:2])
    packed = PackedSACUpdate([a, b])
    for group in packed.groups:
        tensors = [group.param, group.exp_avg, group.exp_avg_sq, group.steps, group.element_slot]
        assert {t.device for t in tensors + [group.target] if t is not None} == {packed.device}
    assert packed.params_finite().device == packed.device
    batches, noises = _batches(seeds[:2], 1)
    assert {n.device for pair in noises[0] for n in pair} == {batches[0][0][0].device}  # the batch's own device
    packed.unpack()
    keyed = PackedSACUpdate._keyed

    def one_on_meta(u):  # seed 1's first critic weight on another device
        out = keyed(u)
        if u is b:
            k = next(k for k in out if k.startswith("critic:"))
            out[k] = (torch.empty(out[k][0].shape, device="meta"), out[k][1])
        return out

    monkeypatch.setattr(PackedSACUpdate, "_keyed", staticmethod(one_on_meta))
    with pytest.raises(AdaRLValueError, match=r"one device: found \['cpu', 'meta'\] .*seed 1 critic:"):
        packed.pack()
    assert not packed.packed and not packed.groups
