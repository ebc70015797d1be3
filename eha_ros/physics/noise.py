"""The torque-motor current noise, drawn outside the kernels.

Named ``noise`` for its one class: :class:`NoiseSource` draws the samples from
``numpy.random.Generator(seed)`` and keeps them, so the kernels (:mod:`.loop`) only read them.
"""

from __future__ import annotations

import numpy as np

__all__ = ['NoiseSource']


class NoiseSource:
    """Band-limited white current noise: held Gaussian samples from a seeded generator.

    Samples are drawn in order and kept, so any run with the same seed sees the same noise
    whatever the chunks it is advanced in.
    """

    def __init__(self, std_a: float, sample_time_s: float, seed: int):
        self.std_a = float(std_a)
        self.sample_time_s = float(sample_time_s)
        self._rng = np.random.default_rng(seed)
        self._samples = np.zeros(0)

    def samples_until(self, t_end_s: float) -> np.ndarray:
        """All samples covering ``[0, t_end_s]`` (drawing more as needed)."""
        need = int(t_end_s / self.sample_time_s) + 2
        if need > self._samples.size:
            extra = max(need - self._samples.size, 1024)
            new = self._rng.standard_normal(extra) * self.std_a
            self._samples = np.concatenate([self._samples, new])
        return self._samples
