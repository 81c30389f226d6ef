"""A road model carried across a robot's frames (``best`` on a stream; issue 27 item 2).

The per-frame model (:mod:`scmr_mesh.imaging.road_model`) learns the road from the regions
covering the bottom-centre cell of each frame.  When that cell is not road (a car close
ahead, a trunk, a person) the seed is wrong and so is the whole mask.  A robot sends a
stream, so it can remember what its road looked like, as the self-supervised road detectors
of the DARPA Grand Challenge did (Dahlkamp et al. 2006 kept a mixture of road Gaussians over
frames, refreshed from each new trusted patch):

* **State** (:class:`RoadTrack`): one Gaussian over the road model's four pixel features
  (mean and covariance, 20 floats), learnt only from the model's own *confident* masks (the
  reply had ``confidence`` 1 and no ``abstained``, or with ``learn_shrunk`` the shrunk mask of
  a frame whose seed reached the horizon or was dim; no label is ever seen), the lower half of
  the mask (the ground nearest the robot), blended into the carried one with the forgetting
  factor ``forget`` (the carried model's weight).
* **Cold start**: an empty track; the frame gets exactly the per-frame model's mask.
* **Warm**: the frame's seed is checked against the track: when at least ``agree`` of the
  seed's pixels in the bottom-centre cell lie inside the track's ``p`` ellipsoid the seed
  *agrees* and the frame gets the per-frame mask (with ``extend``, regions that match the
  track are also road-like).  When it *disagrees*, the regions of the bottom band (the
  cell's rows, full width) that match the track replace the seed and the mask is what is
  connected to them; the frame is not learnt from.
* **Reset**: after ``patience`` frames in a row that disagree or abstain (the road surface
  changed, or the model lost confidence), or when more than ``max_gap_s`` passed since the
  last frame (a new drive): the next frame is a cold start.  The frame that triggers the
  reset keeps the mask computed for it and reports ``carried = "reset"``.

The track is a few hundred bytes (:meth:`RoadTrack.to_dict` / :meth:`RoadTrack.from_dict`);
the imaging core stays pure (numpy, OpenCV).  Its constants (:class:`TrackParams`) are
chosen by leave-one-sequence-out cross-validation on CamVid's drives
(:func:`scmr_mesh.imaging.evaluate.cross_validate_sequences`, ``scmr eval --sequences``).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from scmr_mesh.errors import InputError
from scmr_mesh.imaging.road_model import (
    ABSTAIN_REASONS,
    FEATURE_OFFSET,
    N_FEATURES,
    SHADE_DIRECTION,
    RoadParams,
    abstain,
    chi2_quantile,
    classify,
    connected_to_seeds,
    pixel_features,
)
from scmr_mesh.imaging.steps import bottom_centre, roi

_LIMITS: dict = {}

#: What happened to a frame's road model (``DrivableResult.carried``).
CARRIED = ("cold", "agree", "replaced", "disagree", "reset")


@dataclass(frozen=True)
class TrackParams:
    """The constants of the carried road model.

    The defaults are the in-sample choice of ``scmr eval --sequences --occlude 3`` (docs/ACCURACY.md):
    on CamVid's drives without occluders every combination that leaves ``extend`` off ties with
    the per-frame model, so only the stress test tells them apart.  ``p`` is not in the grid
    (the per-frame model's widest quantile).

    Attributes
    ----------
    forget : float
        Weight of the carried Gaussian when a confident frame is blended in (0 = only the
        last confident frame, close to 1 = a long memory).
    p : float
        Quantile of the chi-square(4) ellipsoid around the carried Gaussian.
    agree : float
        The frame's seed agrees with the track when at least this share of its pixels in the
        bottom-centre cell lies inside the carried ellipsoid; a region of the bottom band
        replaces a disagreeing seed when this share of its pixels does.
    patience : int
        Frames in a row that disagree with the track or abstain before it resets.
    max_gap_s : float
        A frame more than this many seconds after the previous one starts cold (0 = never).
    extend : bool
        On agreeing frames, regions that match the carried Gaussian are road-like too
        (a union with the frame's own seeds); off = the per-frame mask.
    learn_shrunk : bool
        Also learn from frames that abstained because their seed reached the horizon or was
        dim, using the shrunk mask (what the model was sure of); never from a seed that is
        not ground.  Off = learn only from confident frames.
    """

    forget: float = 0.8
    p: float = 0.99
    agree: float = 0.3
    patience: int = 4
    max_gap_s: float = 0.0
    extend: bool = False
    learn_shrunk: bool = False

    def check(self) -> TrackParams:
        if not 0 <= self.forget < 1:
            raise InputError(f"forget must be in [0, 1), got {self.forget}")
        if not 0 < self.p < 1:
            raise InputError(f"p must be in (0, 1), got {self.p}")
        if not 0 < self.agree <= 1:
            raise InputError(f"agree must be in (0, 1], got {self.agree}")
        if (isinstance(self.patience, bool) or not isinstance(self.patience, numbers.Integral)
                or not 1 <= self.patience <= 1000):
            raise InputError(f"patience must be an integer in [1, 1000], got {self.patience}")
        if not (0 <= self.max_gap_s and math.isfinite(self.max_gap_s)):
            raise InputError(f"max_gap_s must be a finite number >= 0, got {self.max_gap_s}")
        return self

    def as_dict(self) -> dict:
        return asdict(self)


class RoadTrack:
    """One robot's carried road appearance: a Gaussian over the road model's features.

    Bounded: 4 means, a 4x4 covariance and three counters, whatever the stream's length.
    Not thread-safe: one track per robot, fed that robot's frames in order.
    """

    __slots__ = ("mean", "cov", "frames", "misses", "last_t")

    def __init__(self) -> None:
        self.reset()
        self.last_t: float | None = None

    def reset(self) -> None:
        """Forget the road (the next frame is a cold start)."""
        self.mean: np.ndarray | None = None
        self.cov: np.ndarray | None = None
        self.frames = 0     # confident frames learnt since the last reset
        self.misses = 0     # frames in a row that disagreed or abstained

    @property
    def warm(self) -> bool:
        return self.mean is not None

    def learn(self, feats: np.ndarray, forget: float) -> None:
        """Blend the Gaussian of ``feats`` ((n, 4), n >= 5) into the track (moment matching)."""
        mu = feats.mean(axis=0)
        cov = np.cov(feats.T)
        if self.mean is None:
            self.mean, self.cov = mu, cov
        else:
            a = float(forget)
            m = a * self.mean + (1 - a) * mu
            d0, d1 = self.mean - m, mu - m
            self.cov = a * (self.cov + np.outer(d0, d0)) + (1 - a) * (cov + np.outer(d1, d1))
            self.mean = m
        self.frames += 1

    def inside(self, feats: np.ndarray, p: float, params: RoadParams) -> np.ndarray:
        """Which rows of ``feats`` lie inside the track's ``p`` ellipsoid (noise and shade terms as a
        seed's in ``road_share_kernel``: the shade term of a sunlit track only on the shaded side)."""
        cov = self.cov + params.noise ** 2 * np.eye(N_FEATURES)
        limit = _LIMITS.get(p)
        if limit is None:
            limit = _LIMITS[p] = chi2_quantile(p, N_FEATURES)
        d = feats - self.mean
        inv = np.linalg.inv(cov)
        q = ((d @ inv) * d).sum(axis=1)
        if self.mean[2] >= math.log(params.sunlit + FEATURE_OFFSET):
            shaded = cov + params.shade ** 2 * np.outer(SHADE_DIRECTION, SHADE_DIRECTION)
            q = np.where(d @ (inv @ SHADE_DIRECTION) < 0, q, ((d @ np.linalg.inv(shaded)) * d).sum(axis=1))
        return q <= limit

    def to_dict(self) -> dict:
        """A JSON-able copy of the state."""
        return {"mean": None if self.mean is None else self.mean.tolist(),
                "cov": None if self.cov is None else self.cov.tolist(),
                "frames": self.frames, "misses": self.misses, "last_t": self.last_t}

    @classmethod
    def from_dict(cls, doc: dict) -> RoadTrack:
        """The inverse of :meth:`to_dict`; ``InputError`` for a malformed state."""
        t = cls()
        try:
            if doc.get("mean") is not None:
                mean = np.asarray(doc["mean"], np.float64).reshape(N_FEATURES)
                cov = np.asarray(doc["cov"], np.float64).reshape(N_FEATURES, N_FEATURES)
                if not (np.isfinite(mean).all() and np.isfinite(cov).all()):
                    raise ValueError("not finite")
                if not np.allclose(cov, cov.T) or np.linalg.eigvalsh(cov).min() <= 0:
                    raise ValueError("cov is not a positive definite covariance")
                t.mean, t.cov = mean, cov
            t.frames, t.misses = int(doc.get("frames", 0)), int(doc.get("misses", 0))
            t.last_t = None if doc.get("last_t") is None else float(doc["last_t"])
        except (TypeError, ValueError, KeyError, AttributeError) as exc:
            raise InputError(f"road track state is malformed ({exc}); start from RoadTrack()") from None
        return t


def tracked_candidate(small: np.ndarray, seg, params: RoadParams, track: RoadTrack, tparams: TrackParams,
                      t: float | None = None, opening=None, flags: dict | None = None):
    """The candidate mask of a working frame with a carried model; the track is updated in place.

    ``opening(candidate)`` is the caller's horizontal opening (applied before abstention, as in
    the per-frame path).  Returns ``(candidate, confidence, abstained, carried)`` with
    ``carried`` one of :data:`CARRIED`.  With a cold track the first three equal the per-frame
    model's exactly.  ``flags``, when given, receives ``open_ground`` (the per-frame abstention's
    open-ground verdict, which the caller's column fill follows).
    """
    if t is not None and track.last_t is not None and tparams.max_gap_s > 0 and t - track.last_t > tparams.max_gap_s:
        track.reset()
    if t is not None:
        track.last_t = float(t)
    opening = opening or (lambda c: c)
    candidate, info = classify(small, seg, params)
    labels = info["labels"]
    carried = "cold"
    feats = None
    if track.warm:
        feats = pixel_features(small)
        inside = track.inside(feats, tparams.p, params)
        k = info["sizes"].size
        t_share = np.bincount(labels.ravel(), weights=inside, minlength=k) / np.maximum(info["sizes"], 1)
        cell = bottom_centre(roi(labels))
        cell_in = bottom_centre(roi(inside.reshape(labels.shape)))
        seed_px = np.isin(cell, info["seeds"])
        agreement = float(cell_in[seed_px].mean()) if seed_px.any() else 0.0
        if agreement >= tparams.agree:
            carried = "agree"
            if tparams.extend:
                road = (info["road_share"] >= params.frac) | (t_share >= params.frac)
                road |= info["weak_joined"]  # what the weak-border join added
                is_seed = np.zeros(k, bool)
                is_seed[info["seeds"]] = True
                road[is_seed] = True
                candidate = connected_to_seeds(road, labels, is_seed, params)
        else:
            # the seed is not the road the robot has been driving on: the bottom band's regions
            # that look like that road seed the frame instead
            band = labels[-max(cell.shape[0], 1):]
            counts = np.bincount(band.ravel(), minlength=k)
            is_seed = (counts > 0) & (t_share >= tparams.agree)
            is_seed[info["seeds"]] = False
            if is_seed.any():
                carried = "replaced"
                road = (t_share >= params.frac) | is_seed
                candidate = connected_to_seeds(road, labels, is_seed, params, anywhere=True)
                # the seed Gaussians (mus, covs) are the rejected seeds': open_ground's front must not
                # take the surface running on to the horizon for theirs
                info = {**{n: v for n, v in info.items() if n not in ("mus", "covs")},
                        "seeds": np.flatnonzero(is_seed), "grounded": True}
                if params.dim > 0:  # the dim test judges the new seeds' grey level
                    grey = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)[is_seed[labels]]
                    info["seed_grey"] = float(grey.mean())
            else:
                carried = "disagree"
    candidate = opening(candidate)
    candidate, confidence, abstained = abstain(candidate, info, params)
    if flags is not None:
        flags["open_ground"] = bool(info.get("open_ground", False))
    confident = abstained is None and confidence >= 1.0
    shrunk_ok = tparams.learn_shrunk and abstained is not None and abstained != ABSTAIN_REASONS[0]
    trusted = carried in ("cold", "agree") and (confident or shrunk_ok)
    if trusted:
        # learn from the lower half of the confident mask (the ground nearest the robot)
        h = labels.shape[0]
        sel = candidate[h // 2:].ravel() > 0
        if np.count_nonzero(sel) > 4 * N_FEATURES:
            feats = pixel_features(small) if feats is None else feats
            track.learn(feats[(h // 2) * labels.shape[1]:][sel], tparams.forget)
        track.misses = 0
    elif track.warm:
        track.misses += 1
        if track.misses >= tparams.patience:
            track.reset()
            carried = "reset"
    return candidate, confidence, abstained, carried
