"""The PPO loop of the RNAC baselines (Zhou et al., 2023): TorchRL's ``ClipPPOLoss`` + GAE on the same perturbed
envs, evaluation, run folder, logging and checkpoints as AdaRL-SAC.

:func:`build_ppo_components` returns the wired pieces for users writing their own loop; :class:`PPOTrainer`
(a :class:`~adarl.training.Trainer`, reusing its episode logging, evaluation, checkpoint and summary code)
runs a recipe with ``algorithm.name: ppo``. ``algorithm.rnac.mode`` picks plain PPO, RNAC-IPM
(:class:`~adarl.baselines.rnac.IPMAdvantage`) or RNAC-DS (:class:`~adarl.baselines.rnac.DoubleSamplingTransform`).

Defaults follow the original RNAC trainer (tliu1997/RNAC): 64-64 tanh networks with its orthogonal init
(``network.<net>.init`` in the recipes), its Gaussian policy (mean ``tanh`` into the box, state-independent
log-std, samples clipped to the action box: :class:`~adarl.baselines.policy.ClippedNormal`), Adam (eps 1e-5) with
a linear learning-rate decay, 2048-frame batches, 10 epochs of 64-sample minibatches, clip 0.2, GAE(0.99, 0.95),
entropy 0.01, gradient clipping 0.5, running observation normalisation, reward scaling and advantage
normalisation over the whole batch. ``algorithm.ppo.policy: tanh_gaussian`` gives TorchRL's tanh-squashed Gaussian
instead; docs/baselines/rnac.md lists what still differs from the original.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from adarl.baselines.init import orthogonal_init_
from adarl.baselines.normalization import RewardScaler, RunningObsNorm
from adarl.baselines.policy import BoxTanh, ClippedNormal
from adarl.baselines.rnac import DoubleSamplingTransform, IPMAdvantage
from adarl import metrics
from adarl.builders import check_device, make_mlp
from adarl.env_state import (
    collector_state_dict,
    env_state_dict,
    gym_rng_state_dict,
    load_collector_state_dict,
    load_env_state_dict,
    load_gym_rng_state_dict,
)
from adarl.envs import dynamics_state_dict, load_dynamics_state_dict
from adarl.policy import policy_specs
from adarl.run_dir import RunDir, null_logger, recipe_fingerprint
from adarl.training import Trainer, _rng_state, _set_rng_state, make_envs, seed_everything

__all__ = ["PPOModules", "PPOComponents", "LinearDecay", "make_ppo_modules", "build_ppo_components", "PPOTrainer",
           "trainer_class", "normalize_advantage_", "simulator_steps_per_frame"]


@dataclass
class PPOModules:
    """Actor, critic, PPO loss and advantage module of one PPO/RNAC agent (``obs_norms`` sit inside actor and
    critic)."""

    actor: ProbabilisticActor
    critic: ValueOperator
    loss: ClipPPOLoss
    advantage: GAE
    obs_norms: list[RunningObsNorm]


@dataclass
class PPOComponents:
    recipe: object
    env: object
    eval_env: object
    modules: PPOModules
    optimizers: dict[str, torch.optim.Optimizer]
    schedulers: dict[str, torch.optim.lr_scheduler.LRScheduler]
    collector: Collector
    reward_scaler: RewardScaler | None
    double_sampling: DoubleSamplingTransform | None
    total_iterations: int
    regularizer: nn.Module | None = None
    adapter: None = None  # no rank adaptation in the PPO loop (the shared Trainer code reads it)
    replay_buffer: None = None
    extras: dict = field(default_factory=dict)

    @property
    def policy(self):
        return self.modules.actor


class LinearDecay:
    """``1 - step / total`` (floored at 0): the original trainer's linear LR decay, as a picklable object so that
    ``LambdaLR.state_dict()`` saves it."""

    def __init__(self, total: int) -> None:
        self.total = max(1, int(total))

    def __call__(self, step: int) -> float:
        return max(0.0, 1.0 - step / self.total)


def _net(in_dim: int, out_dim: int, mlp, parseval, action_dim: int, obs_norm: RunningObsNorm | None, device):
    from adarl.baselines.mlp import variant_kwargs

    body = make_mlp(in_dim, out_dim, num_cells=mlp.num_cells, activation=mlp.activation,
                    low_rank_layers=mlp.low_rank_layers, rank=mlp.rank, device=device,
                    **variant_kwargs(mlp, parseval, action_dim))
    if mlp.init.scheme == "orthogonal":
        orthogonal_init_(body, gain=mlp.init.gain, head_gain=mlp.init.head_gain)
    return nn.Sequential(obs_norm, body) if obs_norm is not None else body


def make_ppo_modules(recipe, env) -> PPOModules:
    """Actor (``algorithm.ppo.policy``: RNAC's clipped Gaussian or TorchRL's tanh-Gaussian, both with a
    state-independent log-std), state-value critic, ``ClipPPOLoss`` and GAE (or RNAC-IPM's shifted GAE) from a
    recipe's ``network`` and ``algorithm`` sections."""
    device = torch.device(recipe.device)
    alg, ppo = recipe.algorithm, recipe.algorithm.ppo
    obs_dim = env.observation_spec["observation"].shape[-1]
    spec = env.action_spec_unbatched if hasattr(env, "action_spec_unbatched") else env.action_spec
    act_dim = spec.shape[-1]
    norms = [RunningObsNorm(obs_dim).to(device), RunningObsNorm(obs_dim).to(device)] if ppo.obs_norm else []
    a, c = recipe.network.actor, recipe.network.critic
    actor_body = _net(obs_dim, act_dim, a, alg.parseval, act_dim, norms[0] if norms else None, device)
    low, high = spec.space.low, spec.space.high
    if ppo.policy == "clipped_gaussian":  # RNAC's: mean = tanh into the box, samples clipped to it
        head, dist_class = [BoxTanh(low, high).to(device)], ClippedNormal
    else:  # TorchRL's tanh-squashed Gaussian
        head, dist_class = [], TanhNormal
    policy = TensorDictModule(
        nn.Sequential(actor_body, *head, AddStateIndependentNormalScale(act_dim, scale_lb=1e-8).to(device)),
        in_keys=["observation"], out_keys=["loc", "scale"],
    )
    actor = ProbabilisticActor(
        policy, in_keys=["loc", "scale"], spec=spec, distribution_class=dist_class,
        distribution_kwargs={"low": low, "high": high}, return_log_prob=True,
    )
    critic = ValueOperator(_net(obs_dim, 1, c, alg.parseval, act_dim, norms[1] if norms else None, device),
                           in_keys=["observation"])
    # 'batch' standardises once per collected batch in PPOTrainer._iteration; 'minibatch' inside the loss
    loss = ClipPPOLoss(actor, critic, clip_epsilon=ppo.clip_epsilon, entropy_bonus=ppo.entropy_coeff > 0,
                       entropy_coeff=ppo.entropy_coeff, critic_coeff=ppo.critic_coeff, loss_critic_type="l2",
                       normalize_advantage=ppo.normalize_advantage == "minibatch", functional=False)
    rn = alg.rnac
    if rn.mode == "ipm":
        advantage = IPMAdvantage(gamma=alg.gamma, lmbda=ppo.gae_lambda, value_network=critic, kappa=rn.kappa,
                                 average_gae=False)
    else:
        advantage = GAE(gamma=alg.gamma, lmbda=ppo.gae_lambda, value_network=critic, average_gae=False)
    return PPOModules(actor, critic, loss, advantage, norms)


def build_ppo_components(recipe) -> PPOComponents:
    """Env (+ RNAC-DS), evaluation env, networks, loss, optimisers, LR decay and collector of a PPO recipe."""
    check_device(recipe.device)
    seed_everything(recipe.seed)
    env, eval_env = make_envs(recipe)
    modules = make_ppo_modules(recipe, env)
    alg, ppo = recipe.algorithm, recipe.algorithm.ppo
    ds = None
    if alg.rnac.mode == "ds":
        rn = alg.rnac
        ds = DoubleSamplingTransform(rn.num_candidates, rn.noise, value_network=modules.critic, seed=recipe.seed + 2)
        env.append_transform(ds)
    optimizers = {
        "actor": torch.optim.Adam(modules.actor.parameters(), lr=alg.lr, eps=ppo.adam_eps),
        "critic": torch.optim.Adam(modules.critic.parameters(), lr=alg.lr, eps=ppo.adam_eps),
    }
    c = recipe.collector
    iterations = math.ceil(c.total_frames / c.frames_per_batch)
    schedulers = {k: torch.optim.lr_scheduler.LambdaLR(o, LinearDecay(iterations if ppo.lr_decay else 10**12))
                  for k, o in optimizers.items()}
    collector = Collector(env, modules.actor, frames_per_batch=c.frames_per_batch, total_frames=-1,
                          device=recipe.device)
    regularizer = None
    if alg.parseval.enabled:
        from adarl.baselines.parseval import ParsevalRegularizer

        pv = alg.parseval
        regularizer = ParsevalRegularizer(modules.loss, lam=pv.lam, s=pv.s, base_width=pv.base_width)
    scaler = RewardScaler(alg.gamma) if ppo.reward_scaling else None
    generator = torch.Generator().manual_seed(recipe.seed + 1)
    return PPOComponents(recipe, env, eval_env, modules, optimizers, schedulers, collector, scaler, ds, iterations,
                         regularizer, extras={"sampling_generator": generator})


@torch.no_grad()
def normalize_advantage_(batch: TensorDictBase, key: str = "advantage", eps: float = 1e-5) -> TensorDictBase:
    """Standardise ``batch[key]`` in place over the whole batch, ``(A - mean) / (std + eps)`` with the unbiased
    std, as RNAC's trainer does once per 2048-frame batch before its epochs (TorchRL's ``ClipPPOLoss`` would do it
    per minibatch). The value target, computed from the raw advantage, is left alone. A one-frame batch has no
    spread: its advantage becomes 0."""
    adv = batch.get(key)
    std = adv.std() if adv.numel() > 1 else torch.zeros((), dtype=adv.dtype, device=adv.device)
    batch.set(key, (adv - adv.mean()) / (std + eps))
    return batch


def simulator_steps_per_frame(recipe) -> int:
    """Environment steps the simulator takes per collected frame: ``m + 1`` for RNAC-DS (it probes ``m`` noisy
    candidates before the real step), 1 otherwise."""
    rn = recipe.algorithm.rnac
    return rn.num_candidates + 1 if recipe.algorithm.name == "ppo" and rn.mode == "ds" else 1


def trainer_class(recipe) -> type[Trainer]:
    """The trainer that runs ``recipe``: :class:`PPOTrainer` for ``algorithm.name: ppo``, else the SAC Trainer."""
    return PPOTrainer if recipe.algorithm.name == "ppo" else Trainer


class PPOTrainer(Trainer):
    """Runs a PPO/RNAC recipe in a run folder; same outputs as the SAC :class:`~adarl.training.Trainer`."""

    def __init__(self, recipe, run_dir: RunDir, *, quiet: bool = False, _resume_state: dict | None = None,
                 _log_from: int | None = None, _read_only: bool = False) -> None:
        self.recipe, self.run_dir, self.quiet = recipe, run_dir, quiet
        self.read_only, self.fingerprint = _read_only, recipe_fingerprint(recipe)
        self.frames = self.updates = self.episodes = self.iterations = 0
        self.last_eval_frames = self.last_ckpt_frames = 0
        self.best_eval = -math.inf
        self.last_return = float("nan")
        self._pending_updates = 0.0
        self.warm_start_frames = 0  # read by the shared summary code; the PPO loop has no warm starts
        # training losses are averaged over logging.log_interval frames (the sums are checkpointed: exact resume)
        self._loss_sums: dict[str, float] = {}
        self._loss_count = 0
        self._last_log_frames = 0
        self._bar = None
        self.c = build_ppo_components(recipe)
        self.logger = null_logger() if _read_only else run_dir.make_logger(recipe, step=_log_from)
        if _resume_state is not None:
            self._load_checked(_resume_state)

    def train(self) -> dict:
        from tqdm.auto import tqdm

        rc, c = self.recipe, self.c
        total = rc.collector.total_frames
        bar = tqdm(total=total, initial=self.frames, unit="frame", disable=self.quiet, dynamic_ncols=True,
                   desc=rc.name)
        start = time.perf_counter()
        self._clock = (start, self.frames, self.updates)
        try:
            for batch in c.collector if self.frames < total else ():
                if batch.ndim == 1:
                    batch = batch.unsqueeze(0)  # [n_envs, T]: GAE runs along the last dimension
                flat = batch.reshape(-1)
                self.frames += flat.numel()
                bar.update(flat.numel())
                self._log_episodes(flat)
                self._log_losses(self._iteration(batch))
                if self.frames - self.last_eval_frames >= rc.eval.interval:
                    self._evaluate()
                if self.frames - self.last_ckpt_frames >= rc.checkpoint.interval:
                    self.save_checkpoint()
                bar.set_postfix(ret=f"{self.last_return:.1f}", upd=self.updates, refresh=False)
                if self.frames >= total:
                    break
        finally:
            bar.close()
        self._log_losses([], flush=True)  # the last partial logging interval
        if self.last_eval_frames != self.frames:
            self._evaluate()
        self.save_checkpoint()
        summary = self._write_summary(time.perf_counter() - start)
        from adarl.report import write_report

        write_report(self.run_dir.path)
        self.close()
        return summary

    def _iteration(self, batch) -> list[dict[str, torch.Tensor]]:
        """Reward scaling, advantages, then ``epochs`` passes of minibatch PPO updates; then the observation
        statistics absorb the batch and the LR decays."""
        c, alg, ppo = self.c, self.recipe.algorithm, self.recipe.algorithm.ppo
        m = c.modules
        if c.reward_scaler is not None:
            batch.set(("next", "reward"), c.reward_scaler(batch.get(("next", "reward")), batch.get(("next", "done"))))
        with torch.no_grad():
            m.advantage(batch)
        if ppo.normalize_advantage == "batch":
            normalize_advantage_(batch)
        flat = batch.reshape(-1)
        n, mb = flat.numel(), ppo.minibatch_size
        gen = c.extras["sampling_generator"]
        losses = []
        for _ in range(ppo.epochs):
            perm = torch.randperm(n, generator=gen)
            for i in range(0, n, mb):
                losses.append(self._update(flat[perm[i:i + mb]]))
        for norm in m.obs_norms:
            norm.update(flat.get("observation"))
        for s in c.schedulers.values():
            s.step()
        self.iterations += 1
        extra = {}
        if isinstance(m.advantage, IPMAdvantage):
            extra["ipm_reward_shift"] = torch.tensor(m.advantage.last_shift)
        if c.double_sampling is not None:
            ds = c.double_sampling
            extra["ds_worst_fraction"] = torch.tensor(ds.worst_picks / max(1, ds.steps))
        if extra:
            losses[-1] = {**losses[-1], **extra}
            for d in losses[:-1]:
                d.update(extra)
        return losses

    def _update(self, minibatch) -> dict[str, torch.Tensor]:
        c, alg = self.c, self.recipe.algorithm
        td = c.modules.loss(minibatch)
        loss = td["loss_objective"] + td["loss_critic"]
        if "loss_entropy" in td.keys():
            loss = loss + td["loss_entropy"]
        if c.regularizer is not None:
            td = c.regularizer.wrap_output(td)
            loss = loss + td["loss_parseval"]
        loss.backward()
        if alg.max_grad_norm is not None:
            for opt in c.optimizers.values():
                for group in opt.param_groups:
                    torch.nn.utils.clip_grad_norm_(group["params"], alg.max_grad_norm)
        for opt in c.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        self.updates += 1
        return {k: td[k].detach() for k in ("loss_objective", "loss_critic", "loss_entropy", "loss_parseval")
                if k in td.keys()}

    def _log_losses(self, losses: list[dict[str, torch.Tensor]], *, flush: bool = False) -> None:
        """Accumulate a batch's minibatch losses; log their means once ``logging.log_interval`` frames have passed
        since the last log (at a batch boundary), and at the end (``flush``). The PPO loop's own, so it does not
        depend on how the SAC Trainer logs."""
        for k in losses[0] if losses else ():
            self._loss_sums[k] = self._loss_sums.get(k, 0.0) + float(torch.stack([d[k] for d in losses]).sum())
        self._loss_count += len(losses)
        if not flush and self.frames - self._last_log_frames < self.recipe.logging.log_interval:
            return
        self._last_log_frames = self.frames
        if self._loss_count:
            for k, total in self._loss_sums.items():
                self.logger.log_scalar(metrics.train(k), total / self._loss_count, step=self.frames)
            self.logger.log_scalar(metrics.TRAIN_UPDATES, self.updates, step=self.frames)
            self.logger.log_scalar(metrics.TRAIN_LR, self.c.optimizers["actor"].param_groups[0]["lr"],
                                   step=self.frames)
        self._log_throughput()
        self._loss_sums, self._loss_count = {}, 0

    def _write_summary(self, elapsed: float) -> dict:
        """The SAC Trainer's summary plus the simulator's cost: RNAC-DS takes ``m + 1`` env steps per frame, so a
        comparison at equal frames gives it ``m + 1`` times the simulator steps of the other methods."""
        summary = super()._write_summary(elapsed)
        per_frame = simulator_steps_per_frame(self.recipe)
        summary["simulator_steps_per_frame"] = per_frame
        summary["simulator_steps"] = self.frames * per_frame
        self.run_dir.write_json("summary.json", summary)
        return summary

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        c = self.c
        return {
            "counters": {"frames": self.frames, "updates": self.updates, "episodes": self.episodes,
                         "iterations": self.iterations, "last_eval_frames": self.last_eval_frames,
                         "pending_updates": 0.0, "best_eval": self.best_eval,
                         "loss_sums": dict(self._loss_sums), "loss_count": self._loss_count,
                         "last_log_frames": self._last_log_frames},
            "actor": c.modules.actor.state_dict(),
            "critic": c.modules.critic.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in c.optimizers.items()},
            "schedulers": {k: s.state_dict() for k, s in c.schedulers.items()},
            "reward_scaler": c.reward_scaler.state_dict() if c.reward_scaler is not None else None,
            "ds_rng": repr(c.double_sampling.rng_state()) if c.double_sampling is not None else None,
            "ds_counts": ([c.double_sampling.worst_picks, c.double_sampling.steps]
                          if c.double_sampling is not None else None),
            "rng": _rng_state(),
            "dynamics": dynamics_state_dict(c.env),
            "sampling_rng": c.extras["sampling_generator"].get_state(),
            # the live episode (exact resume), as the SAC Trainer saves it: simulator + gymnasium state and the
            # collector's carrier and counters
            "env_state": env_state_dict(c.env),
            "collector": collector_state_dict(c.collector),
            "eval_rng": gym_rng_state_dict(c.eval_env),
            "policy_specs": policy_specs(c.env),
        }

    def save_checkpoint(self) -> Path:
        path = self.run_dir.save_checkpoint(self.state_dict(), frames=self.frames,
                                            keep_last=self.recipe.checkpoint.keep_last, replay_buffer=None,
                                            fingerprint=self.fingerprint)
        self.last_ckpt_frames = self.frames
        return path

    def _load_state(self, state: dict) -> None:
        import ast

        c = self.c
        c.modules.actor.load_state_dict(state["actor"])
        c.modules.critic.load_state_dict(state["critic"])
        for k, o in c.optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        for k, s in c.schedulers.items():
            s.load_state_dict(state["schedulers"][k])
        if c.reward_scaler is not None and state.get("reward_scaler") is not None:
            c.reward_scaler.load_state_dict(state["reward_scaler"])
        if c.double_sampling is not None and state.get("ds_rng"):
            c.double_sampling.set_rng_state(ast.literal_eval(state["ds_rng"]))
        if c.double_sampling is not None and state.get("ds_counts") is not None:
            c.double_sampling.worst_picks, c.double_sampling.steps = (int(v) for v in state["ds_counts"])
        cnt = state["counters"]
        self.frames, self.updates, self.episodes = int(cnt["frames"]), int(cnt["updates"]), int(cnt["episodes"])
        self.iterations = int(cnt.get("iterations", 0))
        self._loss_sums = {k: float(v) for k, v in cnt.get("loss_sums", {}).items()}
        self._loss_count = int(cnt.get("loss_count", 0))
        self._last_log_frames = int(cnt.get("last_log_frames", self.frames))
        self.last_eval_frames = int(cnt["last_eval_frames"])
        self.last_ckpt_frames = self.frames
        self.best_eval = float(cnt["best_eval"])
        load_dynamics_state_dict(c.env, state["dynamics"])
        live_episode = load_env_state_dict(c.env, state.get("env_state"))
        if state.get("collector") is not None:
            load_collector_state_dict(c.collector, state["collector"], carrier=live_episode)
        load_gym_rng_state_dict(c.eval_env, state.get("eval_rng"))
        c.extras["sampling_generator"].set_state(state["sampling_rng"])
        _set_rng_state(state["rng"])  # last: nothing after it may draw random numbers
