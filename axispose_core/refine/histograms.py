"""Colour statistics of one object and its surroundings in one image, learned from that image: what lets the
refiner read the real look (saturation, texture, a mesh's wrong colours) that no render shows."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def colour_bins(image_rgb: np.ndarray, bins: int) -> np.ndarray:
    """Each pixel's RGB histogram bin (H,W) int32, `bins` per channel."""
    shift = 8 - int(np.log2(bins))
    q = np.asarray(image_rgb, dtype=np.uint8) >> shift
    return (q[..., 0].astype(np.int32) * bins + q[..., 1]) * bins + q[..., 2]


@dataclass
class ColourHistograms:
    """Normalised foreground and background histograms over `bins`³ colours; empty ones are uniform."""

    foreground: np.ndarray
    background: np.ndarray

    @classmethod
    def empty(cls, bins: int) -> ColourHistograms:
        uniform = np.full(bins**3, 1.0 / bins**3)
        return cls(uniform.copy(), uniform.copy())

    def copy(self) -> ColourHistograms:
        return ColourHistograms(self.foreground.copy(), self.background.copy())

    def learn(self, foreground_bins: np.ndarray, background_bins: np.ndarray, rate: float) -> None:
        """Blend in the colours seen now (bin indices of foreground and background samples) with weight `rate`
        (1: forget what was learned); a side with no samples keeps what it had."""
        n = len(self.foreground)
        self.learn_counts(np.bincount(foreground_bins, minlength=n), np.bincount(background_bins, minlength=n), rate)

    def learn_counts(self, foreground: np.ndarray, background: np.ndarray, rate: float) -> None:
        """`learn` from the samples' counts per bin."""
        for name, seen in (("foreground", foreground), ("background", background)):
            if total := seen.sum():
                setattr(self, name, (1 - rate) * getattr(self, name) + rate * seen.astype(np.float64) / total)

    def posterior(self) -> np.ndarray:
        """P(foreground | colour) per bin with equal priors, 0.5 where neither side has seen the colour."""
        total = self.foreground + self.background
        return np.where(total > 0, self.foreground / np.where(total > 0, total, 1.0), 0.5)
