"""MiniRocket's ridge classifier with probabilities: a softmax of its decision values at the
temperature that fits its own leave-one-out predictions best (the plain ridge only votes,
which leaves nothing to fuse across OA and US and no confidence to print)."""

from __future__ import annotations

import numpy as np
from sklearn.linear_model import RidgeClassifierCV

SCALES = np.logspace(-1, 2.5, 36)  # softmax inverse temperatures tried


class CalibratedRidge(RidgeClassifierCV):
    """RidgeClassifierCV + predict_proba. Construct with store_cv_results=True and a scoring
    (e.g. "accuracy"): only then does scikit-learn keep the leave-one-out decision values;
    without a scoring it keeps their squared errors, which say nothing about the class."""

    def fit(self, X: np.ndarray, y: np.ndarray, sample_weight: object = None
            ) -> CalibratedRidge:
        """Fit the ridge, then the temperature on its efficient leave-one-out values."""
        if not self.store_cv_results or self.scoring is None:
            raise ValueError("CalibratedRidge needs store_cv_results=True and a scoring")
        super().fit(X, y, sample_weight)
        cv = self.cv_results_[..., int(np.argmin(np.abs(np.asarray(self.alphas) - self.alpha_)))]
        self.cv_results_ = None  # (n, classes, alphas) floats: not worth pickling
        truth = np.searchsorted(self.classes_, y)
        rows = np.arange(len(truth))
        loss = [-np.mean(log_softmax(two_columns(cv) * k)[rows, truth]) for k in SCALES]
        self.scale_ = float(SCALES[int(np.argmin(loss))])
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        """(n, classes) probabilities."""
        return np.exp(log_softmax(two_columns(self.decision_function(X)) * self.scale_))


def two_columns(d: np.ndarray) -> np.ndarray:
    """Decision values as (n, classes): a binary ridge gives one column (class 1's)."""
    d = np.asarray(d, float).reshape(len(d), -1)
    return np.hstack([-d, d]) if d.shape[1] == 1 else d


def log_softmax(z: np.ndarray) -> np.ndarray:
    """Row-wise log softmax."""
    z = z - z.max(axis=1, keepdims=True)
    return z - np.log(np.exp(z).sum(axis=1, keepdims=True))
