"""Seeds of one recipe trained side by side in one process, their SAC updates as one batched program.

Why: every experiment here is many seeds of the same recipe, and at (64, 64) one seed's update is bound by per-call
overhead, not arithmetic (docs/performance.md). :class:`SeedPack` runs N seeds' ordinary
:class:`~adarl.runtime.trainers.off_policy.OffPolicyTrainer` loops, each in its own run folder, and hands their
updates to one :class:`~adarl.fast.packed.PackedSACUpdate`, so that each of the update's ~700 operations is one call
for all the seeds.

How: each seed's ``train()`` runs unchanged in a greenlet (a coroutine on the main thread: switches happen only where
this module switches, so signals, RNG states and ordering stay deterministic). A seed runs its loop (collection,
replay, episodes' logs, evaluation, checkpoints, rank events, callbacks) exactly as alone until it needs an update;
then it draws its batch and noise as the fused step would (its sampler, its RNG) and yields to the pack. Once every
live seed has yielded, the pack steps them all at once and resumes each with its own losses. Each seed's global RNGs
(torch, NumPy, Python) are switched in and out with it, so every seed draws the numbers it draws alone.

Before a seed's rank adapter acts, and before a checkpoint, the pack is *unpacked* (each seed owns its tensors and its
optimisers hold its Adam state, as alone); it packs again at the next update. A seed whose training fails (a
divergence that stops it, an error) ends alone: the others go on, re-packed without it. A seed's run folder is file
for file a solo run's, with ``packed_with`` (the pack's run folders) in its summary.json.

Mirrors: N ``OffPolicyTrainer(recipe_i, run_dir_i).train()`` one after another.
Equality: ``tests/test_packed_trainer.py`` (a packed seed's losses and the ranks of its first event against its solo
run's; a diverging seed stopped alone; a signal stops every seed at a checkpoint, and the pack resumes).
"""

from __future__ import annotations

import random
import sys
from collections.abc import Sequence
from pathlib import Path

import greenlet
import numpy as np
import torch
import tqdm

from adarl.errors import AdaRLValueError
from adarl.fast.packed import PackedSACUpdate, packing_refusal
from adarl.runtime.families import family
from adarl.runtime.signals import GracefulInterrupt
from adarl.runtime.trainers.off_policy import OffPolicyTrainer
from adarl.runtime.update import FusedStep

__all__ = ["PackedSeedTrainer", "SeedPack", "SeedRNG", "recipe_without_seed", "pack_refusal", "components_refusal"]


def recipe_without_seed(recipe) -> dict:
    """The recipe as a dict without its ``seed``: what the seeds of one pack must share."""
    data = recipe.model_dump(mode="json")
    data.pop("seed", None)
    return data


def components_refusal(c) -> str | None:
    """Why a seed with the built components ``c`` cannot train in a pack (None: it can)."""
    if not isinstance(c.update, FusedStep):
        return f"{type(c.update).__name__} (packing runs the fused SAC update, algorithm.fused)"
    reason = packing_refusal(c.update.fused)
    if reason is not None:
        return reason
    adapter = c.adapter
    if adapter is not None and not (hasattr(adapter, "interval") and hasattr(adapter, "step_count")):
        return f"the rank adapter {type(adapter).__name__} (packing needs to know when it acts: no interval)"
    return None


def pack_refusal(recipe) -> str | None:
    """Why the seeds of ``recipe`` cannot train in a pack (None: they can), decided as :class:`SeedPack` decides it:
    the recipe's loop must be :class:`OffPolicyTrainer`'s and its components (built here once, then closed) must pass
    :func:`components_refusal`. ``adarl experiment --pack`` asks it once per arm before anything runs."""
    fam = family(recipe)
    loop = fam.trainer_class()
    if loop is not OffPolicyTrainer:
        return f"the {loop.__name__} loop of algorithm.base {recipe.algorithm.base!r} (packing runs OffPolicyTrainer's)"
    c = fam.build(recipe)
    try:
        return components_refusal(c)
    finally:
        c.close()


class SeedRNG:
    """A seed's global RNG states (torch, NumPy, Python; CUDA's once a GPU is in use), switched in and out with its
    greenlet.

    The same states :func:`adarl.runtime.state.rng_state` checkpoints, kept as the objects the RNGs hand out instead
    of converted for a file: this runs at every switch, twice per seed and update."""

    __slots__ = ("torch", "numpy", "python", "cuda")

    def __init__(self) -> None:
        self.save()

    def save(self) -> None:
        self.torch, self.numpy, self.python = torch.get_rng_state(), np.random.get_state(), random.getstate()
        # seeds on a GPU draw their update noise there (FusedSACUpdate.draw_noise): each keeps its own CUDA generators
        self.cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None

    def load(self) -> None:
        torch.set_rng_state(self.torch)
        np.random.set_state(self.numpy)
        random.setstate(self.python)
        if self.cuda is not None:
            torch.cuda.set_rng_state_all(self.cuda)


class _SharedInterrupt:
    """A seed's view of its pack's :class:`~adarl.runtime.signals.GracefulInterrupt`: one handler for the process,
    every seed sees its request and stops after its current batch."""

    def __init__(self, pack: SeedPack) -> None:
        self.pack = pack

    def __enter__(self) -> _SharedInterrupt:
        return self

    def __exit__(self, *exc) -> bool:
        return False

    @property
    def requested(self) -> int | None:
        return self.pack.interrupt.requested if self.pack.interrupt is not None else None

    @property
    def notice(self) -> str:
        return self.pack.interrupt.notice if self.pack.interrupt is not None else ""

    @notice.setter
    def notice(self, value: str) -> None:  # the pack's notice is the pack's: one seed finishing is not the stop's end
        pass

    def stopping(self, what: str) -> None:  # the first seed to stop says it for the pack
        if self.pack.interrupt is not None and self.pack.interrupt.stopping_since is None:
            self.pack.interrupt.stopping("every seed saves its checkpoint, then the pack exits")


class PackedSeedTrainer(OffPolicyTrainer):
    """One seed of a :class:`SeedPack`: an :class:`OffPolicyTrainer` whose updates the pack computes.

    Outside a pack (``pack`` None) it trains as an ``OffPolicyTrainer``."""

    pack: SeedPack | None = None

    def _update(self) -> dict[str, torch.Tensor]:
        if self.pack is None:
            return super()._update()
        step = self.c.update
        batch = step.sampler()  # the indices, then the noise: as FusedStep -> FusedSACUpdate.step draws them
        noise = step.fused.draw_noise(batch[0], batch[1])
        out, finite = self.pack.request(self, batch, noise)
        self.guard.check_losses({k: v for k, v in out.items() if k.startswith("loss_")}, self.updates)
        if not finite:  # the pack checked every seed's parameters in one pass; the guard names what is not finite
            self.guard.check_params(self.updates)
        self.updates += 1
        self.hooks.post_optim(out)
        adapter = self.c.adapter
        if adapter is not None:
            if (adapter.step_count + 1) % adapter.interval == 0:
                self.pack.unpack()  # the adapter reads and replaces this seed's tensors and Adam state
            adapter.step()
        return out

    def save_checkpoint(self, *, scheduled: bool = True) -> Path:
        if self.pack is not None:
            self.pack.unpack()  # the optimisers' state is saved: the seeds' own
        return super().save_checkpoint(scheduled=scheduled)

    def _interrupt(self):
        return _SharedInterrupt(self.pack) if self.pack is not None else super()._interrupt()

    def _summary(self, elapsed: float) -> dict:
        summary = super()._summary(elapsed)
        if self.pack is not None:
            summary["packed_with"] = list(self.pack.names)
        return summary


class SeedPack:
    """N seeds of one recipe (:class:`PackedSeedTrainer`, each in its own run folder) trained in one process.

    ``SeedPack.build(recipe, seeds, run_dirs)`` makes the trainers (each seed's RNGs as its build leaves them);
    :mod:`~adarl.runtime.trainers.pack_folder` makes and continues the pack folders of ``adarl run --pack-seeds`` and
    ``adarl experiment --pack``; :meth:`train` trains them all and returns ``{run folder: summary or the exception
    that ended it}`` (:func:`~adarl.runtime.trainers.pack_folder.finish` turns it into the outcome).

    >>> from adarl.runtime.config import load_recipe
    >>> from adarl.runtime.trainers.pack_folder import create_pack, finish
    >>> recipe = load_recipe("quickstart", ["collector.total_frames=300", "collector.init_random_frames=200",
    ...                                     "collector.frames_per_batch=100", "algorithm.batch_size=32",
    ...                                     "eval.episodes=1", "eval.max_steps=20"])
    >>> pack = create_pack(recipe, [0, 1], "runs/pack", quiet=True)  # runs/pack/seed=0, runs/pack/seed=1
    >>> summaries = finish(pack.train())
    >>> sorted(s["frames"] for s in summaries.values())
    [300, 300]
    """

    def __init__(
        self,
        trainers: Sequence[PackedSeedTrainer],
        rngs: Sequence[SeedRNG],
        *,
        quiet: bool = False,
        names: Sequence[str] | None = None,
    ) -> None:
        self.trainers = list(trainers)
        # what each seed's summary.json calls the runs it was packed with (``packed_with``): their folders, or the
        # names pack.json gives (a run at a URL trains in a scratch folder)
        self.names = [str(t.run_dir.path) for t in self.trainers] if names is None else [str(n) for n in names]
        if len(self.names) != len(self.trainers):
            raise AdaRLValueError(f"one name per seed: {len(self.trainers)} seeds, {len(self.names)} names")
        if not self.trainers:
            raise AdaRLValueError("a seed pack needs at least one seed")
        first = recipe_without_seed(self.trainers[0].recipe)
        for t in self.trainers[1:]:
            if recipe_without_seed(t.recipe) != first:
                diff = sorted(k for k in first if first[k] != recipe_without_seed(t.recipe).get(k))
                raise AdaRLValueError(
                    f"{t.run_dir.path} differs from {self.trainers[0].run_dir.path} in {diff}: the seeds of a pack "
                    "share their recipe but for the seed"
                )
        paths = [t.run_dir.path for t in self.trainers]
        if len(set(paths)) != len(paths):
            raise AdaRLValueError(f"the seeds of a pack need run folders of their own, got {[str(p) for p in paths]}")
        for t in self.trainers:
            if not isinstance(t, PackedSeedTrainer):
                raise AdaRLValueError(f"a seed pack trains PackedSeedTrainer, got {type(t).__name__}")
            reason = components_refusal(t.c)
            if reason is not None:
                raise AdaRLValueError(f"{t.run_dir.path}: packed seeds do not implement {reason}; train it unpacked")
            t.pack = self
        self.rngs = list(rngs)
        self.quiet = quiet
        self.interrupt: GracefulInterrupt | None = None
        self._update: PackedSACUpdate | None = None
        self._members: list[int] = []
        self._requests: dict[int, tuple] = {}

    # ------------------------------------------------------------------ construction
    @classmethod
    def build(cls, recipe, seeds: Sequence[int], run_dirs: Sequence, *, quiet: bool = False) -> SeedPack:
        """A new pack: ``recipe`` with each of ``seeds``, in the run folders ``run_dirs`` (RunDir, one per seed)."""
        if len(seeds) != len(run_dirs):
            raise AdaRLValueError(f"one run folder per seed: {len(seeds)} seeds, {len(run_dirs)} folders")
        if len(set(seeds)) != len(seeds):
            raise AdaRLValueError(f"the seeds of a pack differ from each other, got {list(seeds)}")
        trainers, rngs = [], []
        for seed, run_dir in zip(seeds, run_dirs, strict=True):
            trainers.append(PackedSeedTrainer(recipe.model_copy(update={"seed": int(seed)}), run_dir, quiet=True))
            rngs.append(SeedRNG())  # the RNGs as this seed's build left them, as in its own process
        return cls(trainers, rngs, quiet=quiet)

    # ------------------------------------------------------------------ what the seeds call
    def request(self, trainer: PackedSeedTrainer, batch: tuple, noise: tuple) -> tuple[dict[str, torch.Tensor], bool]:
        """A seed's next update: wait (yield to the pack) until every live seed has asked, then get its losses and
        whether its parameters are all finite."""

        self._requests[self.trainers.index(trainer)] = (batch, noise)
        return greenlet.getcurrent().parent.switch()

    def unpack(self) -> None:
        """Every seed owns its tensors and Adam state again (until the next update packs them)."""
        if self._update is not None:
            self._update.unpack()

    # ------------------------------------------------------------------ the loop
    def _packed(self, members: list[int]) -> PackedSACUpdate:
        fused = [self.trainers[i].c.update.fused for i in members]
        u = self._update
        if u is not None and (members != self._members or any(a is not b for a, b in zip(u.updates, fused))):
            u.unpack()  # a seed left the pack, or rebuilt its components (a rollback)
            u = None
        if u is None:
            u = PackedSACUpdate(fused)
            self._members = members
        elif not u.packed:
            u.pack()
        self._update = u
        return u

    def train(self) -> dict[str, dict | BaseException]:
        """Train every seed to its end; a seed that fails ends alone. Returns each run folder's summary (or error)."""

        results: dict[int, dict | BaseException] = {}
        lets = [greenlet.greenlet(t.train) for t in self.trainers]
        live = set(range(len(self.trainers)))
        outputs: dict[int, dict] = {}
        main_rng = SeedRNG()
        total = sum(t.recipe.collector.total_frames for t in self.trainers)
        bar = tqdm.tqdm(
            total=total,
            initial=sum(t.frames for t in self.trainers),
            unit="frame",
            disable=self.quiet,
            dynamic_ncols=True,
            desc=f"{self.trainers[0].recipe.name} x{len(self.trainers)} seeds",
        )
        with bar, GracefulInterrupt(quiet=self.quiet) as interrupt:
            self.interrupt = interrupt
            try:
                while live:
                    for i in sorted(live):
                        self.rngs[i].load()
                        try:
                            value = lets[i].switch(outputs.pop(i, None)) if i in outputs else lets[i].switch()
                        except KeyboardInterrupt:  # a second signal: every seed stops at once
                            raise
                        except BaseException as err:  # noqa: BLE001 - one seed's end, whatever it is, is its own
                            value, results[i] = None, err
                        finally:
                            self.rngs[i].save()
                        if lets[i].dead:
                            live.discard(i)
                            results.setdefault(i, value)
                            self._requests.pop(i, None)
                    if not self._requests:
                        continue
                    members = sorted(self._requests)
                    update = self._packed(members)
                    batches = [self._requests[i][0] for i in members]
                    noises = [self._requests[i][1] for i in members]
                    self._requests.clear()
                    out = update.step(batches, noises)
                    finite = update.params_finite().tolist()
                    for k, i in enumerate(members):
                        outputs[i] = ({name: v[k] for name, v in out.items()}, finite[k])
                    bar.update(sum(t.frames for t in self.trainers) - bar.n)
            finally:
                self.interrupt = None
                main_rng.load()
                if self._update is not None:
                    self._update.unpack()
                for i in live:  # a stop at once, or an error in the pack itself: end what still runs
                    if lets[i]:
                        try:
                            lets[i].throw(greenlet.GreenletExit)
                        except BaseException:  # noqa: BLE001 - ending it is all that is asked
                            pass
                    try:
                        self.trainers[i].close()
                    except Exception:  # noqa: BLE001 - already closed by its own loop
                        pass
        report = {str(self.trainers[i].run_dir.path): results.get(i) for i in range(len(self.trainers))}
        if not self.quiet:
            for path, res in report.items():
                said = "finished" if isinstance(res, dict) else f"ended: {type(res).__name__}: {res}"
                print(f"adarl: {path} {said}", file=sys.stderr)
        return report
