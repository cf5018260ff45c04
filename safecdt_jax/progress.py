"""One progress bar for the long host-side loops (collection, deployment chunks)."""

from __future__ import annotations


class Bar:
    """A tqdm bar that appears on the first `update` (so a step that turns out to be cached shows
    nothing), or never when `enabled` is False. Use as a context manager; `update(n)` advances."""

    def __init__(self, total: int, desc: str, unit: str = "episode", enabled: bool = True):
        self.total, self.desc, self.unit, self.enabled = total, desc, unit, enabled
        self._bar = None

    def __enter__(self) -> Bar:
        return self

    def update(self, n: int) -> None:
        """Advances the bar by `n` units, creating it first if needed."""
        if not self.enabled:
            return
        if self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=self.desc, unit=self.unit)
        self._bar.update(n)

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.close()
