"""The recipe's ``rank`` section: the adaptive rank controller (paper Alg. 1) and its acceptance step."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from adarl import plugins
from adarl.errors import AdaRLValueError, UnknownNameError, did_you_mean, one_of
from adarl.runtime.config._schema_base import Float, PosInt, _plain_copy, _Problems, _Section, _validated_options


class AcceptConfig(_Section):
    mode: Literal["projection", "always"] = Field(
        "projection",
        description="Algorithm 1's acceptance step (Sec. 4.2): 'projection' applies the rule's candidate only if the "
        "truncated network's outputs on recent transitions change by at most the tolerance (else the layer keeps "
        "its rank, r_new = r_old); 'always' applies every candidate (with rule 'energy': Eq. 10 alone, the literal "
        "ratchet that lowers every rank at every event). Rule 'fixed' is an instruction, not a proposal: always "
        "applied.",
    )
    actor_tol: Annotated[Float, Field(ge=0)] = Field(
        0.05,
        description="Largest relative change of the actor's outputs (distribution parameters) accepted at an event.",
    )
    critic_tol: Annotated[Float, Field(ge=0)] = Field(
        0.02, description="Largest relative change of each critic's Q-values on recent (state, action) pairs accepted."
    )
    search: bool = Field(
        True,
        description="When the candidate is refused, search the ranks between it and the current rank - 1 for the "
        "smallest within the tolerance (false: keep the rank at once).",
    )
    samples: PosInt = Field(
        2048, description="Most recent replay transitions the outputs are compared on (also recorded with 'always')."
    )


class RankConfig(_Section):
    enabled: bool = Field(True, description="Run the adaptive rank controller (false = plain or fixed-rank SAC).")
    truncate: bool = Field(
        True,
        description="false: the events run every `interval` steps and do everything an event that changed a rank "
        "does (LR warm-up from zero, replay.warm_start) but truncate nothing: the control arm that separates AdaRL's "
        "restarts from its truncations (recipes/baselines/*_sac_restarts.yaml); the networks may then be dense.",
    )
    rule: str = Field(
        "energy",
        description="Rank rule, a registered name (adarl.register_rank_rule; installed packages add names through "
        "the 'adarl.plugins' entry-point group): 'energy' = paper Eq. 10; 'energy_inclusive' = smallest rank with "
        "energy >= beta; 'ratio' = Eq. 33 (App. D.4); 'fixed' = target_rank; 'policy_fit' = fit/penalty trade-off "
        "with lam; a plugin's rule takes rule_options (docs/adding-a-component.md).",
        json_schema_extra={
            "allowed": "a registered rank rule name ('energy', 'energy_inclusive', 'ratio', 'fixed', 'policy_fit', "
            "or one an installed plugin adds)"
        },
    )
    rule_options: dict[str, Any] = Field(
        default_factory=dict,
        description="A registered plugin rule's own keyword arguments (its pydantic model: unknown keys, types and "
        "ranges are checked like every other key; every default is written into the run's recipe.yaml). adarl's "
        "own rules have none: they read beta, target_rank and lam.",
    )
    beta: Annotated[Float, Field(gt=0, lt=1)] = Field(
        0.98, description="Energy threshold of the energy and ratio rules (paper: 0.98)."
    )
    target_rank: PosInt | None = Field(None, description="Rank the 'fixed' rule truncates to (required by it).")
    lam: Annotated[Float, Field(ge=0)] = Field(1e-3, description="Rank penalty of the 'policy_fit' rule.")
    interval: PosInt = Field(
        1_000_000,
        description="Optimisation steps between rank events (paper: 1e6; Walker2d 0.7e6).",
    )
    scope: Literal["actor", "critic", "both"] = Field(
        "both", description="Networks the controller truncates (Table 2: 'both' is the most reliable)."
    )
    min_rank: PosInt = Field(1, description="Never truncate below this rank.")
    target_mode: Literal["sync", "project"] = Field(
        "sync",
        description="Target critics after a truncation: 'sync' copies the new online factors; 'project' applies "
        "the same change of basis to the target factors (keeps the Polyak lag).",
    )
    num_threads: Literal["auto"] | PosInt | None = Field(
        "auto",
        description="Torch threads during a rank event (restored afterwards; training is paused anyway): 'auto' = "
        "every core this process may use, or OMP_NUM_THREADS when set (adarl experiment -j N>1 sets 1, Ray and SLURM "
        "cpus_per_run); null = the run's own (algorithm.num_threads). Events on wide layers are float64 "
        "eigendecompositions that scale with cores.",
    )
    accept: AcceptConfig = Field(
        default_factory=AcceptConfig,
        description="Acceptance step: whether the rule's candidate rank is applied (docs/rank-rules.md).",
    )

    @field_validator("rule")
    @classmethod
    def _check_rule_name(cls, v: str) -> str:
        try:
            plugins.rank_rule(v)
        except UnknownNameError as err:
            msg = f"must be one of {one_of(err.allowed)}{did_you_mean(v, err.allowed)}{err.hint}"
            raise _Problems([("", v, msg)]) from None
        except AdaRLValueError as err:  # an installed plugin failed to load (named)
            raise _Problems([("", v, str(err))]) from None
        return v

    @model_validator(mode="after")
    def _check_rule(self) -> RankConfig:
        spec = plugins.rank_rule(self.rule)
        if spec.builtin and self.rule_options:
            raise _Problems(
                [
                    (
                        "rule_options",
                        _plain_copy(self.rule_options),
                        f"must be empty with adarl's own rule {self.rule!r}: set rank.beta, rank.target_rank or "
                        "rank.lam instead (rule_options are a registered plugin rule's keyword arguments)",
                    )
                ]
            )
        self.rule_options = _validated_options(
            spec.options, self.rule_options, "rule_options", f"rank rule {self.rule!r}"
        )
        if self.rule == "fixed":
            if self.target_rank is None:
                raise _Problems([("target_rank", None, "rule 'fixed' needs target_rank: an integer >= 1")])
            if self.target_rank < self.min_rank:
                raise _Problems([("target_rank", self.target_rank, f"must be >= min_rank ({self.min_rank})")])
        return self
