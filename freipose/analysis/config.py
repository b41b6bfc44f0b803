"""Settings of the attribution by classification.

Used by :func:`freipose.analysis.attribution.run_attribution` and its stages.
"""

from __future__ import annotations

from dataclasses import dataclass

from freipose.errors import FreiPoseError

STANDARDIZE = ("recording", "train")


class AttributionConfigError(FreiPoseError):
    """An attribution setting is out of range; the message names the setting."""


@dataclass(frozen=True)
class AttributionConfig:
    """Settings of the attribution (defaults follow the method).

    Attributes:
        C: SVM regularization (method: 0.0025).
        onset_delay_s: frames from ``start + onset_delay_s`` to ``end`` are stimulated.
        margin_s: frames further than this from every window are not stimulated.
        alpha: significance level for Bonferroni-adjusted p-values (method figure: 0.001).
        n_jobs: parallel workers for the single-variable SVMs (joblib; -1 = all cores).
        train_stride: use every n-th labelled train frame (frames are strongly correlated).
        pre_s: the dynamics window starts this many seconds before onset.
        post_s: the dynamics window ends this many seconds after the longest stimulation.
        top: number of top variables whose time courses are reported.
        max_iter: LinearSVC iteration limit.
        block: variables per parallel task.
        independent_frames: test significance counting every frame as an independent
            sample, as the method did (anti-conservative: consecutive frames are correlated);
            by default the chi-squared test uses the effective number of independent frames.
        constant_rtol: a variable whose standard deviation over the train frames is at most
            this fraction of its root mean square is constant up to numerical noise and is
            not used (1e-5: about 100 float32 round-offs; see
            :func:`freipose.analysis.stats.informative_columns`).
        standardize: "recording" (default) z-scores every variable of every recording with
            that recording's own mean and deviation over all its frames before fitting and
            scoring, which removes offsets between recordings (animal size, camera setup)
            that a variable with little variation in the train recording would otherwise
            turn into a constant decision; "train" standardizes with the train frames'
            statistics only (the method's ``StandardScaler``).

    Raises:
        AttributionConfigError: a setting is out of range.
    """

    C: float = 0.0025
    onset_delay_s: float = 0.4
    margin_s: float = 1.5
    alpha: float = 0.001
    n_jobs: int = 1
    train_stride: int = 1
    pre_s: float = 5.0
    post_s: float = 5.0
    top: int = 6
    max_iter: int = 10000
    block: int = 16
    independent_frames: bool = False
    constant_rtol: float = 1e-5
    standardize: str = "recording"

    def __post_init__(self) -> None:
        """Check the ranges of the settings."""
        if self.standardize not in STANDARDIZE:
            raise AttributionConfigError(
                f"standardize must be one of {', '.join(STANDARDIZE)}, got {self.standardize!r}"
            )
        if not 0 <= self.constant_rtol < 1:
            raise AttributionConfigError(
                f"constant_rtol must be in [0, 1), got {self.constant_rtol}"
            )
        if not self.C > 0:
            raise AttributionConfigError(f"C must be > 0, got {self.C}")
        if not 0 < self.alpha < 1:
            raise AttributionConfigError(f"alpha must be in (0, 1), got {self.alpha}")
        if self.train_stride < 1:
            raise AttributionConfigError(f"train_stride must be >= 1, got {self.train_stride}")
        if self.pre_s < 0 or self.post_s < 0:
            raise AttributionConfigError("pre_s and post_s must be >= 0 seconds")
        if self.onset_delay_s < 0 or self.margin_s < 0:
            raise AttributionConfigError("onset_delay_s and margin_s must be >= 0 seconds")
