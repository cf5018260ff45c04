"""Configuration of the Constrained Decision Transformer (CDT) and its LoRA adapters.

One frozen, hashable dataclass holds every architectural number, so a config can be a static
argument of `jax.jit` and two equal configs share one compiled program.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from typing import Any

from safecdt_jax import validate as check
from safecdt_jax.presets import MODEL

PRESET_NAMES: tuple[str, ...] = tuple(MODEL)


@dataclass(frozen=True)
class CDTConfig:
    """Architecture, loss weights and LoRA settings of a CDT (defaults = OSRL's CDT).

    Attributes:
        obs_dim: size of one observation vector.
        act_dim: size of one action vector (actions live in [-max_action, max_action]).
        episode_len: the task's horizon; the timestep embedding has `episode_len + seq_len` rows,
            because training windows that run past an episode's end keep counting timesteps.
        embed_dim: model width (every token and every residual stream has this size).
        num_layers: number of pre-LN transformer blocks.
        num_heads: attention heads per block; `embed_dim` must be a multiple of it.
        seq_len: context length K in timesteps; the transformer sees 4K tokens (R, C, s, a).
        mlp_ratio: hidden width of the block MLP as a multiple of `embed_dim` (OSRL: 4).
        embedding_dropout: dropout on the token sequence after the embedding LayerNorm.
        attention_dropout: dropout on the attention probabilities.
        residual_dropout: dropout on the attention and MLP outputs before each residual add.
        reward_scale: the return-to-go token is the raw return-to-go times this (OSRL: 0.1).
        cost_scale: the cost-to-go input is the raw cost-to-go (cost steps) times this (OSRL:
            1). With `cost_offset` and `cost_transform` this is the whole token encoding, saved
            with every checkpoint, so pretraining, evaluation, deployment and finetuning read
            the tokens one way (docs/METHOD.md section 0).
        cost_transform: if True the scaled cost-to-go input is replaced by `cost_offset - input`
            before its embedding (OSRL's default, with offset 50).
        cost_offset: the constant of the cost transform.
        max_action: half-width of the action box; evaluation actions are clipped to it.
        use_state_head: build the next-state head (OSRL always builds it, so its parameters are
            part of OSRL's parameter count even though its loss weight is 0).
        cost_loss_weight: weight of the 2-class cost classifier's NLL in the training loss.
        state_loss_weight: weight of the next-state MSE in the training loss (0 as in OSRL).
        layernorm_eps: LayerNorm epsilon (PyTorch's default, 1e-5).
        lora_rank: rank r of the LoRA adapters.
        lora_alpha: LoRA alpha; the adapter update is scaled by `lora_alpha / lora_rank`.
        lora_targets: names of the attention projections that get adapters (q and v).
        token_bins: 0 embeds the return-to-go and cost-to-go inputs linearly (OSRL). N > 0
            encodes each as N piecewise-linear ramps (`piecewise_linear`) before its embedding,
            with bin edges fitted to the pretraining data (`return_edges`, `cost_edges`; see
            `safecdt_jax.model.tokens`). Why: the embedding LayerNorm divides each token by its
            own scale, so a linear embedding `w * x` of a positive scalar keeps only its sign
            once `|w * x|` outgrows the bias and the timestep embedding; the ramps turn a
            value into a direction, which the LayerNorm keeps (docs/METHOD.md section 8).
        token_rates: multiply the return-to-go and cost-to-go inputs by `T / (T - t)` (T the
            horizon `episode_len`, t the step): the tokens then read the return and cost per
            step still to come, in whole-episode units. A plain return-to-go of 10 is a careful
            policy's whole episode and a fast one's last quarter; as a rate each policy keeps
            its own value at every step, so the token names the behaviour without the
            timestep embedding's help (docs/METHOD.md section 8).
        constant_targets: False (OSRL): the return and cost tokens are the return- and
            cost-to-go, falling by the realised rewards and costs within an episode, in training
            windows and in rollouts alike. True: every step's tokens hold the episode's t=0 labels
            (its return and cost, or with `PretrainConfig.labels="policy"` its policy's means),
            and a rollout keeps the targets it started with; the tokens then name how an
            episode is driven rather than what is left of it. Why: a conditional clone of
            CarGoal1 expert data follows a constant policy-mean cost label and loses the
            response once the label is decremented; the `cpu` CDT did not follow with it
            alone (docs/METHOD.md section 8). A documented deviation from OSRL;
            not with `token_rates`.
        stochastic_actions: False (OSRL): rollouts act with the Gaussian head's mean, clipped to
            the action box. True: with a sample `mean + exp(log_std) * N(0, 1)` of it, clipped,
            the noise drawn from the episode's step keys. Why: where the behaviour data's cost
            comes from the experts' exploration noise (the Car, whose wheel torques saturate at
            +-0.02 so nearly every sampled action is a sign coin), a clone that acts with its
            mean drives otherwise than the episodes whose labels it was given
            (docs/METHOD.md section 8). Pretraining is unchanged. What `--act checkpoint`
            (None in the Python functions) reads; every entry point acts with samples unless
            told (`analysis.evaluate.DEFAULT_ACTION_MODE`, docs/METHOD.md section 1).
        return_edges: increasing bin edges of the ramps for the return-to-go input (scaled units,
            RTG * reward_scale); empty until fitted. Values outside them saturate.
        cost_edges: the same for the cost-to-go input (CTG * cost_scale, before any transform:
            with ramps `cost_transform` is not applied, an affine flip the ramps do not need).
    """

    obs_dim: int
    act_dim: int
    episode_len: int
    embed_dim: int = 128
    num_layers: int = 3
    num_heads: int = 8
    seq_len: int = 10
    mlp_ratio: int = 4
    embedding_dropout: float = 0.1
    attention_dropout: float = 0.1
    residual_dropout: float = 0.1
    reward_scale: float = 0.1
    cost_scale: float = 1.0
    cost_transform: bool = True
    cost_offset: float = 50.0
    max_action: float = 1.0
    use_state_head: bool = True
    cost_loss_weight: float = 0.02
    state_loss_weight: float = 0.0
    layernorm_eps: float = 1e-5
    lora_rank: int = 16
    lora_alpha: float = 32.0
    lora_targets: tuple[str, ...] = ("query", "value")
    token_bins: int = 0
    token_rates: bool = False
    constant_targets: bool = False
    stochastic_actions: bool = False
    return_edges: tuple[float, ...] = ()
    cost_edges: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        check.integers(self, "obs_dim", "act_dim", "episode_len", "embed_dim", "num_layers",
                       "num_heads", "seq_len", "mlp_ratio", "lora_rank")
        check.integers(self, "token_bins", minimum=0)
        check.booleans(self, "token_rates", "constant_targets", "stochastic_actions",
                       "cost_transform", "use_state_head")
        if self.token_rates and self.constant_targets:
            raise ValueError("CDTConfig.token_rates and constant_targets exclude each other: a "
                             "rate divides what is left, a constant target never shrinks")
        for name in ("return_edges", "cost_edges"):
            edges = getattr(self, name)
            if not isinstance(edges, tuple) or any(
                    not isinstance(e, float) or not math.isfinite(e) for e in edges):
                raise ValueError(f"CDTConfig.{name} must be a tuple of finite floats, "
                                 f"got {edges!r}")
            if edges and (self.token_bins == 0 or len(edges) < 2
                          or any(b <= a for a, b in itertools.pairwise(edges))):
                raise ValueError(f"CDTConfig.{name} must be empty, or (with token_bins > 0) at "
                                 f"least 2 strictly increasing edges, got {edges!r}")
            if len(edges) > self.token_bins + 1:
                raise ValueError(f"CDTConfig.{name} has {len(edges)} edges, more than "
                                 f"token_bins + 1 = {self.token_bins + 1}")
        if self.embed_dim % self.num_heads:
            raise ValueError(
                f"CDTConfig.embed_dim ({self.embed_dim}) must be divisible by "
                f"num_heads ({self.num_heads})"
            )
        check.unit_interval(self, "embedding_dropout", "attention_dropout", "residual_dropout",
                            open_right=True)
        check.positive(self, "max_action", "lora_alpha", "layernorm_eps", "reward_scale",
                       "cost_scale")
        if self.cost_loss_weight < 0 or self.state_loss_weight < 0:
            raise ValueError("CDTConfig loss weights must be non-negative")
        if self.state_loss_weight > 0 and not self.use_state_head:
            raise ValueError("CDTConfig.state_loss_weight > 0 needs use_state_head=True")
        bad = set(self.lora_targets) - {"query", "key", "value", "out"}
        if bad or not self.lora_targets:
            raise ValueError(
                f"CDTConfig.lora_targets must be a non-empty subset of query/key/value/out, "
                f"got {self.lora_targets!r}"
            )

    @property
    def head_dim(self) -> int:
        """Width of one attention head, `embed_dim // num_heads`."""
        return self.embed_dim // self.num_heads

    @property
    def num_timestep_rows(self) -> int:
        """Rows of the absolute-timestep embedding table, `episode_len + seq_len`."""
        return self.episode_len + self.seq_len

    @property
    def lora_scale(self) -> float:
        """Multiplier of the LoRA update `A @ B`, `lora_alpha / lora_rank`."""
        return self.lora_alpha / self.lora_rank

    def replace(self, **changes: Any) -> CDTConfig:
        """Return a copy with `changes` applied (validated again)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def preset(
        cls, name: str, obs_dim: int, act_dim: int, episode_len: int, **overrides: Any
    ) -> CDTConfig:
        """Build a named preset for a task's sizes: `tiny`, `cpu`, `osrl` or `paper`.

        `overrides` replace any field of the preset (e.g. `seq_len=20`). Raises ValueError for an
        unknown name or an invalid value.
        """
        if name not in MODEL:
            raise ValueError(f"unknown CDT preset {name!r}; choose one of {', '.join(MODEL)}")
        fields = {**MODEL[name], **overrides}
        return cls(obs_dim=obs_dim, act_dim=act_dim, episode_len=episode_len, **fields)
