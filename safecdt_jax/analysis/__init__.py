"""Studies of trained models, not stages of the pipeline: how the cost follows its target
(`evaluate`) and which tokens the CDT reads (`diagnose`). Each backs a CLI command (`evaluate`,
`analyze diagnose`) and docs/METHOD.md section 9. Behaviour clones live in `baselines.bc`."""
