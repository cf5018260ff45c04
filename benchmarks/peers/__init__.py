"""Peer benchmark: this project against Safety-Gymnasium 1.0.0 and OSRL's PyTorch CDT.

`setup` installs the peers into virtual environments under `.peers/` (git-ignored), `worker` is
the script that runs inside those environments, `ours` measures the same work on this project's
side, `flops` the arithmetic floor; `benchmarks.run_all` ties them together.
"""
