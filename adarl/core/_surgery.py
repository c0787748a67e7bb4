"""In-place tensor surgery: give a layer's factors a new rank without breaking what holds them.

Why in place: the loss, the policy a collector runs and :class:`~torchrl.objectives.SoftUpdate` all hold the
factor ``Parameter`` objects, so a rank change gives them new ``.data`` (identities kept), drops their now
meaningless optimiser state in every optimiser, gives the target factors the same shape (``"sync"`` copies,
``"project"`` applies the same change of basis) and erases the loss's cached parameter views.
:func:`resize_to_ranks` is the same surgery for a checkpoint load. Re-exported by :mod:`adarl.core.adapter`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable, Mapping, Sequence

import torch
from torch import nn

from adarl.core._sites import LowRankSite, find_low_rank_layers
from adarl.core.lowrank import factor_svd, refactorize
from adarl.core.lowrank import replace_data as _set_data
from adarl.errors import CheckpointError

__all__ = ["TARGET_MODES", "PROJECT_COND_LIMIT", "apply_rank", "follow_shared", "resize_to_ranks"]

TARGET_MODES = ("sync", "project")
#: ``target_mode="project"`` falls back to "sync" when cond(R1) or cond(R2) exceeds this (float64).
PROJECT_COND_LIMIT = 1e6


def _erase_loss_caches(loss: nn.Module) -> None:
    """Drop the loss's cached detached / stacked parameter views (they would still point at the old tensors)."""
    cache = loss.__dict__.get("_cache")
    if isinstance(cache, dict):
        cache.clear()
    erase = getattr(loss, "_erase_cache", None)
    if callable(erase):
        erase()


def _forget_optimizer_state(optimizers: Iterable[torch.optim.Optimizer], tensors: Iterable[torch.Tensor]) -> None:
    tensors = list(tensors)
    for opt in optimizers:
        for t in tensors:
            opt.state.pop(t, None)


def _project_basis(w1: torch.Tensor, w2: torch.Tensor, rank: int):
    """The online rank-``rank`` factors and the change of basis that produced them (float64, batched).

    ``W1 = Q1 R1``, ``W2^T = Q2 R2``, ``R1 R2^T = Uc S Vch``. The new online factors are
    ``W1' = Q1 Uc_k sqrt(S_k) = W1 T'`` and ``W2' = sqrt(S_k) Vch_k Q2^T = T W2`` with
    ``T' = R1^-1 Uc_k sqrt(S_k)`` (r x k) and ``T = sqrt(S_k) Vch_k R2^-T`` (k x r). Returns
    ``(W1', W2', T', T, cond)`` where ``cond`` is the worst condition number of R1/R2. The online factors come
    from this same decomposition (not from :func:`factor_svd`, whose singular vectors may differ by signs) so that
    the target factors ``W1t T'``, ``T W2t`` stay in the online factors' basis: SoftUpdate lerps them elementwise.
    """
    a = w1.detach().to(torch.float64)
    b = w2.detach().to(torch.float64)
    q1, r1 = torch.linalg.qr(a, mode="reduced")
    q2, r2 = torch.linalg.qr(b.transpose(-1, -2), mode="reduced")
    cond = max(float(torch.linalg.cond(r1).max()), float(torch.linalg.cond(r2).max()))
    uc, s, vhc = torch.linalg.svd(r1 @ r2.transpose(-1, -2), full_matrices=False)
    root = s[..., :rank].sqrt()
    left = uc[..., :, :rank] * root.unsqueeze(-2)  # Uc_k sqrt(S_k), r x k
    right = root.unsqueeze(-1) * vhc[..., :rank, :]  # sqrt(S_k) Vch_k, k x r
    new_w1 = q1 @ left
    new_w2 = right @ q2.transpose(-1, -2)
    if not math.isfinite(cond):
        return new_w1, new_w2, None, None, cond
    t_right = torch.linalg.solve_triangular(r1, left, upper=True)
    t_left = torch.linalg.solve_triangular(r2, right.transpose(-1, -2), upper=True).transpose(-1, -2)
    return new_w1, new_w2, t_right, t_left, cond


def _resize_site(site: LowRankSite, w1: torch.Tensor, w2: torch.Tensor, optimizers) -> None:
    """Give a site's online, target and template factors new values (in place, identities kept)."""
    _set_data(site.w1, w1)
    _set_data(site.w2, w2)
    _forget_optimizer_state(optimizers, (site.w1, site.w2))
    if site.extra is not None:
        e1, e2 = site.extra
        lead = (0,) * len(site.batch_shape)
        _set_data(e1, w1[lead].clone())
        _set_data(e2, w2[lead].clone())
        _forget_optimizer_state(optimizers, (e1, e2))


def _padded_factors(u, s, vh, rank: int, width: int, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Rank-``rank`` factors stored at width ``width`` (zero columns/rows beyond ``rank``)."""
    s = s.clone()
    s[..., rank:] = 0
    return refactorize(u, s, vh, width, dtype)


def apply_rank(site: LowRankSite, rank: int, u, s, vh, target_mode: str, optimizers) -> str | None:
    """Re-factorise ``site`` at ``rank`` from its SVD ``(u, s, vh)``, targets included; returns how the targets were
    given the new shape (``target_mode``, or why it fell back to ``"sync"``), None without targets."""
    dtype = site.w1.dtype
    mode = None
    w1 = w2 = t1 = t2 = None
    if site.target_w1 is not None:
        mode = target_mode
        if mode == "project":
            p1, p2, t_right, t_left, cond = _project_basis(site.w1, site.w2, rank)
            if not math.isfinite(cond) or cond > PROJECT_COND_LIMIT:
                mode = f"sync (fallback: cond(R1, R2) = {cond:.3g} > {PROJECT_COND_LIMIT:.0g})"
            else:
                tw1 = site.target_w1.detach().to(torch.float64)
                tw2 = site.target_w2.detach().to(torch.float64)
                t1, t2 = tw1 @ t_right, t_left @ tw2
                if torch.isfinite(t1).all() and torch.isfinite(t2).all():
                    w1, w2 = p1.to(dtype), p2.to(dtype)
                else:
                    mode, t1, t2 = "sync (fallback: non-finite projected target)", None, None
    if w1 is None:
        w1, w2 = refactorize(u, s, vh, rank, dtype)
    _resize_site(site, w1, w2, optimizers)
    if site.target_w1 is not None:
        if t1 is None:
            t1, t2 = w1.clone(), w2.clone()
        _set_data(site.target_w1, t1)
        _set_data(site.target_w2, t2)
    return mode


def follow_shared(site: LowRankSite, peers: Iterable[tuple[Sequence[LowRankSite], nn.Module, Sequence]]) -> list[str]:
    """After ``site`` was resized, bring every other loss that trains the same factors along (issue 29.2).

    Two losses may share one network (TorchRL's own tests build several losses on one actor): the factor
    ``Parameter`` objects are then the same, but each loss has its own target factors, cached views and optimisers.
    ``peers``: ``(sites, loss, optimizers)`` of the other adapters. Each site of theirs holding ``site``'s factors
    gets its targets synced to the new online factors (their own lag is in another basis), its template's own
    factors resized, its optimisers' state of those factors dropped and its loss's caches erased. Returns the paths
    of the peers' layers that followed, as ``"<loss class>.<path>"``."""
    followed = []
    for sites, loss, optimizers in peers:
        touched = False
        for other in sites:
            if other is site or other.w1 is not site.w1:
                continue
            _forget_optimizer_state(optimizers, (site.w1, site.w2))
            if other.extra is not None and other.extra[0].shape != site.w1.shape[len(site.batch_shape) :]:
                lead = (0,) * len(site.batch_shape)
                _set_data(other.extra[0], site.w1.detach()[lead].clone())
                _set_data(other.extra[1], site.w2.detach()[lead].clone())
                _forget_optimizer_state(optimizers, other.extra)
            if other.target_w1 is not None and other.target_w1 is not site.target_w1:
                _set_data(other.target_w1, site.w1.detach().clone())
                _set_data(other.target_w2, site.w2.detach().clone())
            touched = True
            followed.append(f"{type(loss).__name__}.{other.path}")
        if touched:
            _erase_loss_caches(loss)
    return followed


def resize_to_ranks(
    loss_module: nn.Module,
    ranks: Mapping,
    optimizers: torch.optim.Optimizer | Sequence[torch.optim.Optimizer] = (),
) -> dict[str, tuple[int, int]]:
    """Give a freshly built loss the ranks of a checkpoint, so ``loss.load_state_dict`` can load it.

    A rank event changes parameter *shapes*; ``loss.load_state_dict`` of a truncated checkpoint into a freshly
    built (full-rank) loss fails, even with ``strict=False``. Call this first::

        resize_to_ranks(loss, checkpoint["adapter"], optimizer)   # or checkpoint["loss"], or {path: rank}
        loss.load_state_dict(checkpoint["loss"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        adapter.load_state_dict(checkpoint["adapter"])

    ``ranks`` may be ``{layer_path: rank}`` (see :attr:`RankAdapter.ranks`), a :meth:`RankAdapter.state_dict`
    (its ``"ranks"``) or the loss's own ``state_dict()`` (ranks read from the ``w2`` shapes). Every LowRankLinear of
    the loss (actor and critics, online, stacked ensemble, targets, template) is resized in place (``.data``; the
    values are a truncated projection, or zero-padded when growing, and are meant to be overwritten by the load),
    and the optimiser state of resized parameters is dropped (``optimizer.load_state_dict`` restores it).
    Returns ``{layer_path: (old_rank, new_rank)}`` for the resized layers.
    """
    if isinstance(optimizers, torch.optim.Optimizer):
        optimizers = [optimizers]
    sites, searched = find_low_rank_layers(loss_module, "both")
    if not sites:
        raise CheckpointError(f"no LowRankLinear layers found in {type(loss_module).__name__}; searched {searched}")
    by_path = {s.path: s for s in sites}
    wanted = _ranks_from_source(ranks, sites)
    unknown = sorted(set(wanted) - set(by_path))
    if unknown:
        raise CheckpointError(f"checkpoint has ranks for unknown layers {unknown}; this model has {sorted(by_path)}")
    changed: dict[str, tuple[int, int]] = {}
    with torch.no_grad():
        for path, rank in wanted.items():
            site = by_path[path]
            if isinstance(rank, bool) or not isinstance(rank, int) or not 1 <= rank <= site.max_rank:
                raise CheckpointError(f"rank for {path!r} must be an integer in [1, {site.max_rank}], got {rank!r}")
            old = site.rank
            if rank == old and (site.target_w1 is None or int(site.target_w2.shape[-2]) == rank):
                continue  # (a loss sharing its actor with one resized before: the targets still need the shape)
            if rank != old:
                w1, w2 = _resized(site.w1, site.w2, rank)
                _resize_site(site, w1, w2, optimizers)
            if site.target_w1 is not None:
                t1, t2 = _resized(site.target_w1, site.target_w2, rank)
                _set_data(site.target_w1, t1)
                _set_data(site.target_w2, t2)
            changed[path] = (old, rank)
    if changed:
        _erase_loss_caches(loss_module)
    return changed


def _resized(w1: torch.Tensor, w2: torch.Tensor, rank: int) -> tuple[torch.Tensor, torch.Tensor]:
    old = int(w2.shape[-2])
    u, s, vh = factor_svd(w1, w2)
    a, b = refactorize(u, s, vh, min(rank, old), w1.dtype)
    if rank > old:
        pad = rank - old
        a = torch.cat([a, a.new_zeros(*a.shape[:-1], pad)], -1)
        b = torch.cat([b, b.new_zeros(*b.shape[:-2], pad, b.shape[-1])], -2)
    return a, b


def _ranks_from_source(source: Mapping, sites: list[LowRankSite]) -> dict[str, int]:
    if not isinstance(source, Mapping):
        raise CheckpointError(
            f"ranks must be a mapping (ranks, adapter state_dict or loss state_dict), got {type(source)}"
        )
    if "ranks" in source and isinstance(source["ranks"], Mapping):
        source = source["ranks"]
    if any(isinstance(v, torch.Tensor) for v in source.values()):
        out = {}
        for site in sites:
            owner = f"{site.network_name}_params" if site.params is not None else site.network_name
            key = ".".join(p for p in (owner, site.module_path, "w2") if p)
            if key in source:
                out[site.path] = int(source[key].shape[-2])
        if not out:
            raise CheckpointError(
                "the state_dict holds no LowRankLinear factor of this model (no '...w2' keys matched)"
            )
        return out
    bad = {k: v for k, v in source.items() if isinstance(v, bool) or not isinstance(v, numbers.Integral)}
    if bad:
        raise CheckpointError(f"ranks must be integers, got {bad}")
    try:
        return {str(k): int(v) for k, v in source.items()}
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"cannot read ranks from {type(source).__name__}: {err}") from None
