"""Studies of trained models, not stages of the pipeline: how the cost follows its target
(`evaluate`), which tokens the CDT reads (`diagnose`), and per-step behaviour clones of the data
(`bc`). Each backs a CLI command (`evaluate`, `diagnose`, `bc`) and docs/CDT_FINDINGS.md."""
