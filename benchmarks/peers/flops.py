"""Matmul FLOPs of the CDT, counted one way for both sides (the floor of comparison 5).

Only matrix products are counted (2 m n k each): embeddings, q/k/v, attention scores and
weighted sums, output projections, MLPs and heads. Layer norms, softmax and GELU are left out;
they are a few percent here. The tools' own counters are not used as the common measure:
PyTorch's `FlopCounterMode` does not see the fused attention that `nn.MultiheadAttention` runs in
evaluation mode, and XLA's `cost_analysis` counts every element-wise op too; `run_all` prints
both beside this count as a cross-check.
"""

from safecdt_jax.model import CDTConfig


def forward_flops(cfg: CDTConfig, batch: int, steps: int, last_rows: int | None = None) -> float:
    """FLOPs of one forward over `steps` timesteps (4 tokens each) for `batch` windows.

    `last_rows`: how many token rows the last block computes (None = all, the plain forward;
    1 = our rollout's trimmed pass, which needs only the newest state token's action). The
    heads run on the rows that come out: OSRL's forward applies its action, cost and state heads
    to every step; the trimmed pass applies only the action head, to one row.
    """
    d, n, h = cfg.embed_dim, 4 * steps, cfg.embed_dim * cfg.mlp_ratio
    mm = lambda rows, k, m: 2.0 * rows * k * m
    total = mm(steps, cfg.obs_dim, d) + mm(steps, cfg.act_dim, d) + 2 * mm(steps, 1, d)
    for layer in range(cfg.num_layers):
        rows = n if last_rows is None or layer < cfg.num_layers - 1 else last_rows
        total += mm(n, d, 2 * d) + mm(rows, d, d)  # keys and values of all tokens, queries
        total += 2 * mm(rows, n, d)  # scores and weighted values, all heads together
        total += mm(rows, d, d) + mm(rows, d, h) + mm(rows, h, d)  # out projection, MLP
    if last_rows is None:  # OSRL: Gaussian (mean, log std), cost and next-state heads per step
        total += mm(steps, d, 2 * cfg.act_dim) + mm(steps, d, 2) + mm(steps, d, cfg.obs_dim)
    else:
        total += mm(last_rows, d, 2 * cfg.act_dim)
    return batch * total


def rollout_step_flops(cfg: CDTConfig, horizon: int, trimmed: bool) -> float:
    """Mean model FLOPs per env step of one episode at batch 1.

    OSRL's rollout feeds the unpadded prefix (1, 2, ... K steps, then K); ours always feeds a
    left-padded K-step window through the trimmed pass.
    """
    if trimmed:
        return forward_flops(cfg, 1, cfg.seq_len, last_rows=1)
    return sum(forward_flops(cfg, 1, min(t + 1, cfg.seq_len)) for t in range(horizon)) / horizon


def lora_flops_per_step(cfg: CDTConfig, horizon: int, lora_steps: int, lora_batch: int) -> float:
    """Adapter training FLOPs per env step: `lora_steps` updates of `lora_batch` windows after
    each `horizon`-step episode. Each update: the forward, the backward to the activations (one
    forward's matmuls again) and the weight gradient of the adapted (merged) kernels only, 2 x
    tokens x D^2 each: the frozen base's weight gradients are never computed (XLA's count of
    the adapter gradient is 2.03-2.09 forwards against 2.92-2.96 for all parameters, tested in
    `tests/test_deploy_finetune.py`)."""
    tokens = lora_batch * 4 * cfg.seq_len
    adapted = cfg.num_layers * len(cfg.lora_targets) * 2 * tokens * cfg.embed_dim ** 2
    return lora_steps * (2 * forward_flops(cfg, lora_batch, cfg.seq_len) + adapted) / horizon
