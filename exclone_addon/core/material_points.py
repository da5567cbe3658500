"""Material points: image points tracked by optical flow beside FaceMesh's points (docs/method.md
§11).

FaceMesh's points are a regression to a face prior: on rendered ICT heads with the head still
they follow the brows, frowns, pucker and cheekPuff by 0.2-0.5 of the located motion. The image
itself moves with the face: where it has texture (painted brows, lip and lid edges, nostrils),
pyramidal Lucas-Kanade follows those shapes at 0.75-1.1 of it. At calibration the fit's own
points that lie on texture and face the camera become material points, located in the model where
the fit put them (the calibrated neutral plus its slide at that frame's pose, and no slide
after). Each frame tracks them from the previous frame (forward-backward checked; on a thread of
its own while FaceMesh runs) and refits FaceMesh's fit's shape parameters to them too, at its
pose: those parameters drive the weights.

The flow follows the frames less their blur: the shading, which stays with the light as the
head turns, would hold the points back. Tracked from frame to frame they still drift as the head
turns (on the rendered takes the flow reads about 0.92 of a frame's motion where the light stays
with the camera, 0.86 on the frames themselves: 1.4 px off after half a second of turning; 1.5 px
even against the neutral frame warped by the true motion), so after each
frame every point is pulled a share of the way to where FaceMesh's fit puts it: FaceMesh holds
what stays, the flow adds what changes quickly. The share grows with how far the head's motion
moved the point since the frame before (the flow's error grows with it): with the head still
the flow keeps the expressions FaceMesh follows only part of the way. The flow's error lies
mostly along that motion (it reads part of it), so across it the pull is smaller: an expression
that moves a point across the head's motion is kept. The head pose stays
FaceMesh's fit's (with the material points in the pose the rotation's error grew from 1.6 to
1.8-2.7 deg median).

Where FaceMesh's fit puts a point is not where its texture goes as the head turns: on the
rendered turning take (a neutral face) the points' true projections lie 2.0 px median from it
(the flow 2.2 px from the truth, the pull holding the two 1.0 px apart), and fed the true
projections the refit reads the turn as expression (browDown to 1.0). That error follows the
turn point by point (a linear fit in the turn's sines leaves 0.67 of its 2.17 px rms): the
located depth (FaceMesh's, 0.33 cm median absolute deviation) and FaceMesh's pose (1.4 deg
median off). So the refit carries a turn and shift of the material points' own, and each
point's depth along its calibration ray is refined from its residuals over the take.
"""
from dataclasses import replace

import cv2
import numpy as np
from scipy.linalg import cho_factor, cho_solve

from .tracking import TUKEY_CUTOFF, by_model_point, robust_sigma, skew_rows, tukey_weights

# A point is on texture where the image's smaller structure-tensor eigenvalue over 5x5 pixels
# (cv2.cornerMinEigenVal, Sobel 3) exceeds this: about 140 of the 468 points on a 640x480 render.
MIN_TEXTURE = 1e-4
# At most this many points (the most textured): the flow's time grows with them (a photograph's
# face has texture at 360 of the 468; 150 points take about 1 ms on 2 cores).
MAX_POINTS = 150
# Points the fit sees at a slant (facing cosine below this) are not tracked: their window mixes
# the face and what lies behind its silhouette.
MIN_FACING = 0.5
# A tracked point counts only when tracking it back lands within this of where it started.
FORWARD_BACKWARD_PX = 0.7
# After each frame each point moves part of the way to FaceMesh's fit: this share per pixel the
# head's motion (the fit's pose against the frame before's) moved it, at most PULL_MAX. The flow's
# error grows with the motion it follows (on the rendered turning take, tracked from the true
# points, 0.16 px median a frame at 0.37 px of motion, reading 0.92 of it; 0.006 px with the head
# still), and what the pull takes back of it, it takes of the expressions too (FaceMesh follows
# the brows, frowns and pucker 0.2-0.5 of the way): a fixed share of 0.2 cost the head-still take
# 0.64 against 0.75 of correlation with none. 0.3 per pixel held the drift best while the flow
# followed the frames with their shading, 0.25 since it follows them less it (docs/method.md §11).
PULL_PER_PX = 0.25
PULL_MAX = 0.3
# Across the head's motion (per point, its projection's move since the frame before) the pull
# takes this share of what it takes along it: the flow's error lies mostly along the motion it
# under-reads, and an expression moving a point across it is kept. On the rendered takes (moving /
# identity 7 / still; the turning face's largest weight, its 95th percentile per frame) the whole
# pull across (1.0) 0.548 / 0.633 / 0.731, 0.60 / 0.481; 0.3: 0.592 / 0.674 / 0.743, 0.57 / 0.462;
# none (0.0): 0.616 / 0.696 / 0.746, 0.60 / 0.525, and after a wide calibration 0.63
# (mouthStretch_R) against 0.51-0.56 (docs/method.md §11).
ACROSS_SHARE = 0.3
# A material point's weight in the fit against one of FaceMesh's (their noise is a fraction of
# FaceMesh's; fewer of them).
WEIGHT = 20.0
# The frames are cropped to the points' box grown by this before the flow (a face moves a few
# pixels a frame; the flow's 11-pixel window at its coarsest level, a quarter of the size, spans
# about 20).
CROP_MARGIN_PX = 32
# The flow follows each frame less its blur over this many pixels: the shading, which stays where
# the light is as the head turns, is out of it and the painted and modelled detail in (on the
# rendered turning take the flow then reads 0.92 of a frame's motion, not 0.86, and drifts 1.39 px
# median over 15 frames, not 1.58). The detail is scaled by SHADING_GAIN into 8 bits (the flow
# takes 8-bit frames; the strongest edges clip).
SHADING_SIGMA_PX = 5.0
SHADING_GAIN = 4.0
LUCAS_KANADE = dict(winSize=(11, 11), maxLevel=2,
                    criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
# The face's motion from the frame before (MaterialPoints.motion), and the points' own turn and
# shift in the refit, are read from at least this many tracked points.
MIN_MOTION_POINTS = 10
# Each point's depth along its calibration ray is refined from its residuals as the head turns,
# against a prior of (residual spread / depth error spread)^2 in px^2 per cm^2: 1 px against 0.3 cm
# (the located points' relative depth error on the rendered turning take's calibration: 0.33 cm
# median absolute deviation). At 50 cm a 10 deg turn moves a point 2.2 px per cm of depth, so the
# prior weighs about two such frames.
DEPTH_PRIOR = (1.0 / 0.3) ** 2


def without_shading(gray):
    """8-bit `gray` less its Gaussian blur (SHADING_SIGMA_PX), scaled by SHADING_GAIN about 128:
    the image the flow follows."""
    # in 16 bits at 16 steps a grey level (half the time of float32; the blur keeps its fraction)
    image = gray.astype(np.int16) * np.int16(16)
    return cv2.addWeighted(image, SHADING_GAIN / 16, cv2.GaussianBlur(image, (0, 0), SHADING_SIGMA_PX),
                           -SHADING_GAIN / 16, 128.0, dtype=cv2.CV_8U)


class MaterialPoints:
    """The material points of one calibrated take and the shape fit that reads them.

    gray: the calibration's last frame (8-bit); fit: its FitResult by `fitter` (the calibrated
    FaceMesh fitter)."""

    def __init__(self, gray, fit, fitter):
        height, width = gray.shape
        texture = cv2.cornerMinEigenVal(gray, 5, 3)
        pixels = np.clip(np.round(fit.points2d).astype(int), 0, [width - 1, height - 1])
        model = fitter.model
        facing = model.facing(fit.shape, fit.rotation, fit.translation)
        strength = texture[pixels[:, 1], pixels[:, 0]]
        chosen = strength > MIN_TEXTURE
        if facing is not None:
            chosen &= facing > MIN_FACING
        # the FaceMesh point each one started at: the most textured MAX_POINTS
        self.indices = np.sort(np.flatnonzero(chosen)[np.argsort(-strength[chosen])[:MAX_POINTS]])
        slide = model.pose_offset(fit.rotation, fit.translation)
        # located where the fit put them, slide included: the image point stays on the face
        self.located = fit.shape[self.indices] + (0.0 if slide is None else slide[self.indices])
        self._model = model
        self._camera = fitter.camera
        self._min_scale_px = fitter.min_scale_px
        # the chosen points' modes (m, 3, K)
        self._modes = np.ascontiguousarray(model.modes[:, self.indices].transpose(1, 2, 0))
        self._gray = gray
        self.points = fit.points2d[self.indices].astype(np.float32)
        self.motion = None
        # each point's ray from the camera at calibration, in the model's axes: along it the
        # located depth is a guess (FaceMesh's); across it the image placed the point
        seen = fit.rotation.apply(self.located) + fit.translation
        self._ray = fit.rotation.inv().apply(seen / np.linalg.norm(seen, axis=1)[:, None])
        # the depth's least squares over the take so far: sum of slope.slope, of slope.residual
        self._depth_normal = np.zeros(len(self.indices))
        self._depth_moment = np.zeros(len(self.indices))
        self.depth = np.zeros(len(self.indices))     # cm along the ray from the located point
        self._pose = None            # the frame before's fit's pose (rotation, translation)

    def track(self, gray):
        """(m, 2) the material points in this frame (NaN where not found or not trusted). Sets
        `motion`: the 2x3 similarity (pixels) the tracked points moved by from the frame
        before, robustly fitted (RANSAC); None when too few were tracked."""
        tracked = np.full((len(self.indices), 2), np.nan)
        self.motion = None
        if self._gray is not None:
            # both frames cropped about the points: the flow's pyramids cover the face only
            height, width = gray.shape
            low = np.maximum(np.floor(self.points.min(axis=0)) - CROP_MARGIN_PX, 0).astype(int)
            high = np.minimum(np.ceil(self.points.max(axis=0)) + CROP_MARGIN_PX,
                              [width, height]).astype(int)
            crop = np.s_[low[1]:high[1], low[0]:high[0]]
            before, now = without_shading(self._gray[crop]), without_shading(gray[crop])
            start = self.points - low.astype(np.float32)
            ahead, found, _ = cv2.calcOpticalFlowPyrLK(before, now, start, None, **LUCAS_KANADE)
            back, found_back, _ = cv2.calcOpticalFlowPyrLK(now, before, ahead, None, **LUCAS_KANADE)
            valid = ((found[:, 0] == 1) & (found_back[:, 0] == 1)
                     & (np.linalg.norm(back - start, axis=1) < FORWARD_BACKWARD_PX))
            tracked[valid] = ahead[valid] + low
            if np.count_nonzero(valid) >= MIN_MOTION_POINTS:
                self.motion = cv2.estimateAffinePartial2D(start[valid], ahead[valid])[0]
                if self.motion is not None:
                    # from the crop's pixels back to the frame's
                    self.motion[:, 2] += low - self.motion[:, :2] @ low
            self.points = np.where(valid[:, None], tracked, self.points).astype(np.float32)
        self._gray = gray
        return tracked

    def fit(self, tracked, fit):
        """FaceMesh's `fit` with its shape parameters refitted to the material points `tracked`
        (m, 2; NaN: not seen; None: none) too, at its pose: one Gauss-Newton step from the fit's
        optimum, its own normal matrix plus the material points' (the projection is nearly
        linear in the parameters at a fixed pose; FaceMesh's gradient there is nought).

        The material points' rows carry a small turn and shift of their own, solved beside the
        shape and dropped: FaceMesh's pose is a degree or two off, and the texture's view of it
        is not an expression. Each point's depth along its calibration ray is then refined by
        its residuals (least squares over the take against DEPTH_PRIOR): a depth error moves a
        point only as the head turns away from calibration's pose, which the shape would read
        as expression. The points then move part of the way to where `fit` puts them: PULL_PER_PX
        per pixel the head's motion since the frame before moved each (at most PULL_MAX), along
        that motion; across it ACROSS_SHARE of that."""
        rotation, matrix = fit.rotation, fit.rotation.as_matrix()
        modes = self._modes
        material = self.located + self.depth[:, None] * self._ray + modes @ fit.params
        turned = rotation.apply(material)
        anchor = self._camera.project(turned + fit.translation)
        if tracked is None:
            tracked = np.full(anchor.shape, np.nan)
        valid = np.all(np.isfinite(tracked), axis=1)
        params = fit.params
        if np.count_nonzero(valid) >= MIN_MOTION_POINTS:
            size = len(params)
            projection = self._camera.jacobian(turned[valid] + fit.translation)
            by_point = by_model_point(projection, matrix)
            # d pixels / d [shape, omega, t]: omega turns on the left as in ShapeFitter
            rigid = np.empty((len(projection), 3, 6))
            rigid[:, :, :3] = -skew_rows(turned[valid])
            rigid[:, :, 3:] = np.eye(3)
            jac = np.concatenate((by_point @ modes[valid], projection @ rigid),
                                 axis=2).reshape(-1, size + 6)
            residuals = tracked[valid] - anchor[valid]
            distance = np.linalg.norm(residuals, axis=1)
            trust = tukey_weights(distance,
                                  TUKEY_CUTOFF * robust_sigma(distance, self._min_scale_px))
            normal = (jac.T * np.repeat(WEIGHT * trust, 2)) @ jac
            normal[:size, :size] += fit.shape_normal
            gradient = jac.T @ (residuals * WEIGHT * trust[:, None]).reshape(-1)
            step = cho_solve(cho_factor(normal, check_finite=False), gradient, check_finite=False)
            params = params + step[:size]
            # the depth: its pixel slope (zero at calibration's pose), against the residual
            # from the located point's own depth
            slope = (by_point @ self._ray[valid][:, :, None])[..., 0]
            from_located = residuals + slope * self.depth[valid, None]
            self._depth_normal[valid] += trust * np.einsum("ij,ij->i", slope, slope)
            self._depth_moment[valid] += trust * np.einsum("ij,ij->i", slope, from_located)
            self.depth = self._depth_moment / (self._depth_normal + DEPTH_PRIOR)
        pull = np.zeros(anchor.shape)
        if self._pose is not None:
            moved = anchor - self._camera.project(self._pose[0].apply(material) + self._pose[1])
            distance = np.linalg.norm(moved, axis=1)
            direction = np.divide(moved, distance[:, None], out=np.zeros_like(moved),
                                  where=distance[:, None] > 0)
            toward = anchor - tracked
            along = np.einsum("ij,ij->i", toward, direction)[:, None] * direction
            toward = along + ACROSS_SHARE * (toward - along)
            pull = np.minimum(PULL_PER_PX * distance, PULL_MAX)[:, None] * toward
        self._pose = (rotation, fit.translation)
        self.points = np.where(valid[:, None], tracked + pull, anchor).astype(np.float32)
        return replace(fit, params=params, shape=self._model.shape(params))
