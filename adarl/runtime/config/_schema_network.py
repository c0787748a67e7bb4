"""The recipe's ``network`` section: the actor's and critics' MLPs, their low-rank layers, sparse layer and
initialisation."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, model_validator

from adarl.runtime.config._schema_base import NonNegInt, PosFloat, PosInt, _Problems, _Section


class SparseLayerConfig(_Section):
    layer: NonNegInt | None = Field(
        None,
        description="Hidden layer replaced by the sparsification layer of Tiwari et al. (2025): a wide linear layer "
        "whose activations keep only the k largest units per input (docs/baselines/sparsification.md); null = none.",
        json_schema_extra={"allowed": "null or a hidden-layer index 0 .. len(num_cells)-1 not in low_rank_layers"},
    )
    width: PosInt = Field(1024, description="Units of the sparsification layer (the paper: 1024).")
    k: PosInt | None = Field(
        None,
        description="Active units per input; null = 2 * action_dim + 1, the paper's bound on the attainable-state "
        "manifold dimension.",
        json_schema_extra={"allowed": "null or an integer >= 1, <= width"},
    )

    @model_validator(mode="after")
    def _check_k(self) -> SparseLayerConfig:
        if self.k is not None and self.k > self.width:
            raise _Problems([("k", self.k, f"must be <= width ({self.width})")])
        return self


class InitConfig(_Section):
    scheme: Literal["default", "orthogonal", "independent_factors"] = Field(
        "default",
        description="Initial weights: 'default' = each layer's own (PyTorch's nn.Linear, LowRankLinear's factorised "
        "nn.Linear init: the balanced SVD of a dense draw); 'orthogonal' = torch.nn.init.orthogonal_ with gain on the "
        "hidden layers and head_gain on the output layer, zero biases, every critic of an ensemble drawn apart (the "
        "RNAC and Parseval originals); 'independent_factors' = each factorised layer's W1 and W2 drawn apart as the "
        "bias-free nn.Linear pair of the paper's Fig. 5 would start (Kaiming-uniform at each factor's fan-in; biases "
        "and other layers their own; needs low_rank_layers). adarl.baselines.init.",
    )
    gain: PosFloat = Field(
        1.0,
        description="Gain of the hidden layers' orthogonal init: singular values = gain, so W W^T starts at gain^2 I "
        "where rows <= columns (RNAC's trainer: 1; Parseval's code: sqrt(2) = 1.4142135623730951, i.e. s = 2). "
        "Used by scheme 'orthogonal' only.",
    )
    head_gain: PosFloat = Field(
        1.0,
        description="Gain of the output layer's orthogonal init (both originals: 0.01 for the policy head, 1 for the "
        "value head). Used by scheme 'orthogonal' only.",
    )


class MLPConfig(_Section):
    num_cells: list[PosInt] = Field(
        default_factory=lambda: [64, 64],
        min_length=1,
        description="Hidden widths; the paper uses (64, 64) for actor and critic.",
    )
    activation: Literal["relu", "tanh", "softplus", "elu", "gelu"] = Field(
        "relu", description="Hidden activation; the paper uses ReLU (Softplus gives the same results, App. D.5.4)."
    )
    low_rank_layers: list[NonNegInt] = Field(
        default_factory=lambda: [0, 1],
        description="Hidden layers factorised as W1 @ W2 (layer i maps num_cells[i-1] -> num_cells[i], layer 0 "
        "maps the input); the paper factorises the first two.",
        json_schema_extra={"allowed": "a list of distinct hidden-layer indices 0 .. len(num_cells)-1"},
    )
    rank: PosInt | list[PosInt] | None = Field(
        None,
        description="Initial rank of the factorised layers: one integer for all, or one per layer in the order of "
        "low_rank_layers (sorted), e.g. [9, 30] for the ranks another run ended with; null = full rank (the rank "
        "controller then shrinks it).",
        json_schema_extra={
            "allowed": "null, an integer >= 1 <= the smallest width of the low-rank layers, or a list of one such "
            "integer per low-rank layer (each <= that layer's width)"
        },
    )
    sparse: SparseLayerConfig = Field(
        default_factory=SparseLayerConfig, description="Optional sparsification layer (Tiwari et al. baseline)."
    )
    init: InitConfig = Field(
        default_factory=InitConfig, description="Initial weights (orthogonal for the RNAC and Parseval baselines)."
    )

    def layer_max_ranks(self) -> dict[int, int]:
        """Largest rank each low-rank layer can have, as far as known before the env's input size is: the smaller
        of the layer's input and output widths (layer 0: its output width only)."""
        n = len(self.num_cells)
        caps = {}
        for i in self.low_rank_layers:
            if 0 <= i < n:
                caps[i] = self.num_cells[i] if i == 0 else min(self.num_cells[i - 1], self.num_cells[i])
        return caps

    def layer_ranks(self) -> dict[int, int | None]:
        """``{layer: initial rank}`` of each low-rank layer (``None`` = full rank), from one rank or a list."""
        layers = sorted(self.low_rank_layers)
        if isinstance(self.rank, list):
            return dict(zip(layers, self.rank))
        return {i: self.rank for i in layers}

    def max_rank(self) -> int | None:
        """The smallest initial rank of the factorised layers if set, else the smallest known layer width (None: no
        layer)."""
        caps = self.layer_max_ranks()
        if not caps:
            return None
        ranks = [caps[i] if r is None else r for i, r in self.layer_ranks().items() if i in caps]
        return min(ranks) if ranks else min(caps.values())

    @model_validator(mode="after")
    def _check_layers(self) -> MLPConfig:
        problems: list[tuple[str, Any, str]] = []
        n = len(self.num_cells)
        bad = [i for i in self.low_rank_layers if i >= n]
        if bad:
            problems.append(
                (
                    "low_rank_layers",
                    self.low_rank_layers,
                    f"each entry must index a hidden layer, 0 .. {n - 1} (num_cells has {n} entries); "
                    f"out of range: {bad}",
                )
            )
        dup = sorted({i for i in self.low_rank_layers if self.low_rank_layers.count(i) > 1})
        if dup:
            problems.append(("low_rank_layers", self.low_rank_layers, f"entries must be distinct; repeated: {dup}"))
        if not problems and isinstance(self.rank, list):
            caps = self.layer_max_ranks()
            layers = sorted(self.low_rank_layers)
            if len(self.rank) != len(layers):
                problems.append(
                    (
                        "rank",
                        self.rank,
                        f"has {len(self.rank)} entries but low_rank_layers {layers} has {len(layers)}: give one rank "
                        "per low-rank layer (in that order) or a single integer",
                    )
                )
            else:
                for i, r in zip(layers, self.rank):
                    if r > caps[i]:
                        problems.append(
                            ("rank", self.rank, f"layer {i}'s rank {r} must be <= {caps[i]}, the layer's width")
                        )
        elif not problems and self.rank is not None and self.low_rank_layers:
            caps = self.layer_max_ranks()
            cap = min(caps.values())
            if self.rank > cap:
                layer = min(caps, key=lambda i: caps[i])
                problems.append(
                    (
                        "rank",
                        self.rank,
                        f"must be <= {cap}, the smallest width of the low-rank layers (layer {layer}: "
                        + (
                            f"{self.num_cells[layer - 1]} -> {self.num_cells[layer]}"
                            if layer
                            else f"input -> {self.num_cells[0]}"
                        )
                        + ")",
                    )
                )
        if self.init.scheme == "independent_factors" and not self.low_rank_layers:
            problems.append(
                (
                    "init.scheme",
                    self.init.scheme,
                    "'independent_factors' draws the factors of the low-rank layers, and low_rank_layers is empty: "
                    "factorise a layer or use 'default' or 'orthogonal'",
                )
            )
        sp = self.sparse.layer
        if sp is not None:
            if sp >= n:
                problems.append(
                    ("sparse.layer", sp, f"must index a hidden layer, 0 .. {n - 1} (num_cells has {n} entries)")
                )
            elif sp in self.low_rank_layers:
                problems.append(
                    (
                        "sparse.layer",
                        sp,
                        f"is also in low_rank_layers {self.low_rank_layers}; a layer is either "
                        "low-rank or the sparsification layer",
                    )
                )
        if problems:
            raise _Problems(problems)
        return self


class NetworkConfig(_Section):
    actor: MLPConfig = Field(
        default_factory=MLPConfig, description="Policy network (tanh-Gaussian or categorical head)."
    )
    critic: MLPConfig = Field(default_factory=MLPConfig, description="Q network (each of num_qvalue_nets copies).")
