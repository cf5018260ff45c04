"""Experiments: scripts that measure what the method and the environments do (not how fast).

Each is run from the repository root as `python -m experiments.NAME --help` and writes one
result file, `experiments/results/NAME.json` (most with a markdown table beside it); a rerun
overwrites it, and git keeps the earlier ones. Their statistics live in `safecdt_jax.stats`.

    cost_following   does the pretrained CDT's cost follow its cost target in the source task
    levers           Safe-CDT's levers over pretraining x deployment seeds, per pair
    sim2sim          our MJX envs against native Safety-Gymnasium (needs the peer venv)
    vase_models      pushable discs in JAX against MJX contact vases
    lora_response    how online LoRA finetuning moves the cost-target response
"""
