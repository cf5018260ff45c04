"""The named presets, `tiny`, `cpu`, `osrl` and `paper`, in one place: the CDT's sizes and token
encoding (`MODEL`, read by `model.CDTConfig.preset`) and its pretraining run (`PRETRAIN`, read by
`pretrain.default_pretrain`), with the reasons behind each choice.
"""

from __future__ import annotations

from typing import Any

# Sizes of the named presets: (embed_dim, num_layers, num_heads, seq_len, lora_rank, lora_alpha).
MODEL: dict[str, dict[str, Any]] = {
    # Smallest model that still exercises every code path (multi-head, padding, LoRA); for tests.
    "tiny": dict(embed_dim=16, num_layers=1, num_heads=2, seq_len=4, lora_rank=4, lora_alpha=8.0),
    # Default demo model (176,974 parameters for CarGoal, 140,846 for CarCircle, ramps included;
    # 175,054 and 138,926 with linear tokens): its default
    # pretraining, 10,000 updates at batch 32 (pretrain.default_pretrain), takes 2.5-5 minutes on
    # a 2-core CPU at 14-24 ms per update; one batch-15 inference step takes ~1.5 ms.
    # Its cost token reads `5 - 0.1 CTG`, OSRL's `50 - CTG` divided by 10. The embedding
    # LayerNorm normalises each token on its own: an input of size ~50 times a N(0, 0.02) weight
    # swamps the bias and the timestep embedding, and the normalised token keeps little more
    # than the sign of `50 - CTG`. OSRL's 100,000 updates of 2048 windows learn their way around
    # this; 10,000 of 32 did not. On CarCircle1 (scripted collector v4, cost targets 10/20/40/80
    # at the reference return, 20 episodes each) the cost rose with the target and stayed below
    # the data median at target 20 for 3 of 4 pretraining seeds at 0.1, 1 of 3 at scale 1.
    # Since 2026-12-04 its return and cost tokens are 16 ramps each (edges fitted in
    # pretraining) held constant over an episode: with the pretraining defaults of
    # `pretrain.default_pretrain("cpu")` and the experts' sampled actions, the options under which
    # its cost follows the cost target on CarGoal1 and CarCircle1 (PointCircle1: 2 of 4 seeds;
    # docs/METHOD.md sections 8-9).
    "cpu": dict(embed_dim=64, num_layers=2, num_heads=4, seq_len=10, cost_scale=0.1,
                cost_offset=5.0, token_bins=16, constant_targets=True),
    # OSRL's default CDT: 744,910 parameters for CarGoal (obs 72, act 2, episode 1000).
    "osrl": dict(embed_dim=128, num_layers=3, num_heads=8, seq_len=10),
    # The Safe-CDT paper's model: about 3.5M parameters, LoRA rank 16 on q/v -> 65,536 adapters.
    "paper": dict(embed_dim=256, num_layers=4, num_heads=8, seq_len=10),
}


# Defaults per model preset. `cpu`: 10,000 updates of 32 windows. On the 2-core CPU an update
# takes 14-24 ms at batch 32 but 52-80 ms at 64 (the batch-64 activations spill the 1 MB per-core
# L2), and at equal wall time batch 32 reached a better log-likelihood than 64 on collected
# CarGoal1 data; so pretraining takes ~2.5 min on an idle box, ~4-5 min when the cores are shared
# (benchmarks/train_throughput.py). `osrl` and `paper` use OSRL's full schedule, meant for an
# accelerator. The token encoding (RTG and CTG scales, the cost offset) belongs to the model:
# `CDTConfig`.
PRETRAIN: dict[str, dict[str, Any]] = {
    "tiny": dict(steps=200, batch_size=16),
    # Policy-mean labels, a relabelled copy of every episode, normalised inputs and outputs:
    # with the model preset's constant ramp tokens, what makes the cost follow its target
    # (docs/METHOD.md section 8).
    "cpu": dict(steps=10_000, batch_size=32, labels="auto", relabel_percent=1.0,
                scale_actions=True, standardize_obs=True, return_span=(-50.0, 100.0),
                cost_span=(0.0, 100.0)),
    "osrl": dict(steps=100_000, batch_size=2048),
    "paper": dict(steps=100_000, batch_size=2048),
}


# Windows per pass on a CPU backend, per preset. An update runs fastest on a CPU in passes small
# enough that their activations stay in cache: at batch 2048 (`osrl` preset, one thread) passes
# of 8-16 windows took half the time of one pass, 2.2-2.3x OSRL's step; the `paper` preset's
# model gains 1.7x at batch 256 (docs/PERFORMANCE.md). The `cpu` preset's batch of 32 already
# fits (passes of 8-16 gained nothing there), so it stays one pass. Accelerators want the whole
# batch in one pass.
CPU_MICRO_BATCH = {"osrl": 16, "paper": 16}
