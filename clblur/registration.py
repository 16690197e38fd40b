"""Registration of an exposure series: the translation and turn between hand-held exposures.

Why: calibration and the study compare the same pixel across exposures.  A bracket shot by
hand (or on a tripod nudged by the mirror or the photographer) moves by pixels to tens of
pixels between frames, and then every comparison mixes two scene points: on the Canon 400D
bracket shrunk to 1/4, shifts of up to 6 px raised the fitted Eq. 3 rate ``k`` by 17 to 23 %
and quadrupled the held-out error (``docs/studies/memorial-calibration.md``, hand-held
brackets; ``bench/bench_registration.py``).  A hand-held camera also rolls: a turn of 1
degree moves the corners of a 10 MP frame by 40 px however well the centre is registered.

Conventions
-----------
* The motion between exposures is a whole-pixel translation (the hand-held case of Ward,
  "Fast, robust image registration for compositing high dynamic range photographs from
  hand-held exposures", JGT 8(2), 2003), or, where a link turns, a rigid motion (a turn
  and a translation).  Parallax and scale are not modelled; a residual below a pixel is
  what the study's ``misregistration`` effect measures.  Codes are kept as stored: a
  whole-pixel move crops, and a turned frame is read at the pixel nearest to where each
  window pixel's point lies (at most half a pixel off, as a whole-pixel shift is for a
  sub-pixel move); resampling would blend codes.
* **Turns** (rotation).  After a link's whole-pixel shift, the overlap is cut into
  ``_GRID`` x ``_GRID`` blocks (at most ``_BLOCK`` px a side) and each block's whole-pixel
  shift is found as the frame's is.  The rigid motion that carries the most blocks within
  ``_COARSE_PX`` (``_consensus``: of the motions two blocks fix exactly; a block that moved
  otherwise, a stripe that cannot tell its own direction, a subject that moved, is left
  out) is fitted to them.  Where it moves the frame's corners by less than ``TURN_PX / 2``
  (a tripod's: every block moves as the frame does) the link is its whole-pixel shift, so
  a turn that moves no block by a whole pixel goes unseen.  Else the blocks are measured
  ``_REFINE`` times more against the shorter frame carried back by the fit so far
  (bilinear, for the measurement only): what is left is a fraction of a pixel, placed by
  the parabola through the correlations either side of the peak, and the fit is made
  again (the blocks within ``_FIT_PX`` of it).  The turn is applied when it moves the
  frame's corners by more than ``TURN_PX`` and is at least three standard errors (the
  blocks' scatter about the fit); else the link is its whole-pixel shift.  A link with
  fewer than ``_MIN_BLOCKS`` blocks that agree (a frame mostly clipped or dark), or whose
  turn is within three standard errors, keeps its shift: its turn is not told, and where
  another link turned that is reported (``Registration.untold``).
* Criterion: the normalised cross-correlation of the two images' codes over the pixels
  neither clips (codes strictly inside ``(_LOW, _HIGH)`` of full scale in each image; masked
  NCC, Padfield, "Masked object registration in the Fourier domain", IEEE TIP 21(5), 2012).
  A response is monotone, so at the right shift the codes of the two exposures rise
  together; a region where one image is dark and flat (a pedestal and its noise, as in
  Memorial's shortest frames) has little variance and so little say, where the median
  threshold bitmaps of Ward's method turn its noise into structure.
* Search: all shifts up to a quarter of the side at the pyramid level whose longer side is
  at most ``_SEARCH_SIDE`` px (by FFT, every shift at once), then a 3 x 3 step at each finer
  level around the doubled shift.  A link whose best correlation is below ``MIN_NCC``, or
  whose compared pixels are fewer than ``MIN_PIXELS``, is not trusted: its shift is taken as
  zero and reported (``Registration.unregistered``).  Of shifts whose correlations lie
  within ``TIE_NCC`` of the best, the shortest is taken (a ramp or a stripe cannot say how
  far it moved along itself).
* The middle channel is compared (green in RGB and BGR).  Neighbours in exposure are
  registered to each other (they share the most unclipped pixels) and the shifts chained to
  the middle exposure.
* The aligned series is every image cropped to the window all of them cover (views, no
  copy, where every link is a whole-pixel shift; with no shift the images are returned as
  they are).  With a turn the links are chained as maps, and the window is the largest
  one, shrunk side by side from the whole frame, that every map keeps inside its image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clblur.errors import InputError
from clblur.pixels import imax

__all__ = ["MIN_NCC", "MIN_OVERLAP", "MIN_PIXELS", "TIE_NCC", "TURN_PX", "Registration",
           "align_series", "describe", "pair_shift", "summary"]

MIN_NCC = 0.3  # least correlation of a trusted link
MIN_PIXELS = 256  # least compared pixels (at the search level) of a trusted link
MIN_OVERLAP = 16  # px: least side of the window registered images share (or the image's)
TIE_NCC = 1e-3  # correlations this close cannot choose between shifts
_LOW, _HIGH = 0.02, 0.98  # clipped: at or beyond these fractions of full scale
_SEARCH_SIDE = 512  # px: the longer side of the level searched whole
TURN_PX = 0.5  # a link's turn is applied when it moves a pixel of the frame by more than this
_GRID = 3  # blocks per side whose shifts measure a link's turn
_BLOCK = 256  # px: the largest block side (its search reaches a quarter of it, 64 px)
_MIN_BLOCK = 48  # px: the smallest block side; smaller frames are taken as not turned
_MIN_BLOCKS = 4  # blocks that must agree on a turn (``_consensus``)
_FIT_PX = 1.0  # px: a block agrees with a turn that carries it this close
_COARSE_PX = 3.0  # px: the same for the blocks' first, whole-pixel shifts
_REFINE = 2  # times the blocks are measured again against b carried back by the fit


@dataclass(frozen=True)
class Registration:
    """Where each image of a series lies against the middle exposure, and the common window.

    ``shifts``: n x 2 int, (rows, cols): the scene point at ``(y, x)`` of the reference is at
    ``(y + dy, x + dx)`` of image ``i`` (with a turn: at the reference's centre, rounded);
    ``window``: (row slice, col slice) of the reference covered by every image;
    ``reference``: the index of the middle exposure; ``unregistered``: indices of the images
    whose link to their longer neighbour could not be trusted (module Conventions; taken as
    zero); ``maps``: None when every image is a whole-pixel translation of the reference,
    else n x 2 x 3 float64, the affine map of each image (a turn and a translation) that
    carries the reference's ``(x, y, 1)`` to where image ``i`` shows that point;
    ``untold``: with ``maps``, the images whose link's turn could not be told (too few
    blocks agree, a frame mostly dark or clipped: taken as none, module Conventions)."""

    shifts: np.ndarray
    window: tuple[slice, slice]
    reference: int = 0
    unregistered: tuple[int, ...] = ()
    maps: np.ndarray | None = None
    untold: tuple[int, ...] = ()

    @property
    def moved(self) -> bool:
        return bool(np.any(self.shifts)) or self.maps is not None

    def turn_degrees(self, index: int) -> float:
        """The angle of image ``index``'s map, degrees (x to the right, y down; 0 without a
        turn)."""
        if self.maps is None:
            return 0.0
        m = self.maps[index]
        return math.degrees(math.atan2(m[1, 0], m[0, 0]))

    def crop(self, image: np.ndarray, index: int) -> np.ndarray:
        """Image ``index`` cut to the common window: a view where it is a whole-pixel
        translation of the reference, else each window pixel takes the code of the image's
        pixel nearest to where its map carries it (codes as stored, none blended)."""
        rows, cols = self.window
        if self.maps is None:
            dy, dx = self.shifts[index]
        else:
            m = self.maps[index]
            dx, dy = m[:, 2]
            if not (np.array_equal(m[:, :2], np.eye(2)) and dx == int(dx) and dy == int(dy)):
                return _nearest(image, m, rows, cols)
            dy, dx = int(dy), int(dx)
        return image[rows.start + dy:rows.stop + dy, cols.start + dx:cols.stop + dx]


def _nearest(image: np.ndarray, m: np.ndarray, rows: slice, cols: slice) -> np.ndarray:
    """``image`` read at the nearest pixel to ``m (x, y, 1)`` for every ``(y, x)`` of the
    window (the window lies inside: ``clblur.registration._chain_window``)."""
    import cv2

    at = m.copy()
    at[:, 2] += m[:, :2] @ (cols.start, rows.start)
    size = (cols.stop - cols.start, rows.stop - rows.start)
    # OpenCV's nearest neighbour rounds the position (in 1/1024 px steps); warpAffine takes
    # at most 4 channels, so wider images go four at a time
    planes = [image] if image.ndim == 2 or image.shape[2] <= 4 else \
        [image[..., c:c + 4] for c in range(0, image.shape[2], 4)]
    out = [cv2.warpAffine(np.ascontiguousarray(p), at, size,
                          flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) for p in planes]
    out = [o[..., None] if o.ndim == 2 and p.ndim == 3 else o
           for o, p in zip(out, planes, strict=True)]
    return out[0] if len(out) == 1 else np.concatenate(out, axis=2)


def _plane(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The compared channel, float32 in [0, 1] of full scale, and its unclipped mask."""
    im = image if image.ndim == 2 else image[..., min(image.shape[2], 3) // 2]
    g = im.astype(np.float32) / np.float32(imax(image.dtype))
    return g, (g > _LOW) & (g < _HIGH)


def _half(g: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The next pyramid level: 2 x 2 means, a pixel compared when all four were."""
    import cv2

    size = (g.shape[1] // 2, g.shape[0] // 2)
    return (cv2.resize(g, size, interpolation=cv2.INTER_AREA),
            cv2.resize(m.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999)


def _moments(a, ma, b, mb) -> np.ndarray:
    """Masked NCC and pixel count of ``a`` against ``b`` read at the same pixels (same
    shape), as an array (ncc, n)."""
    m = ma & mb
    n = int(np.count_nonzero(m))
    if n < 2:
        return np.array([-np.inf, n])
    x, y = a[m].astype(np.float64), b[m].astype(np.float64)
    x -= x.mean()
    y -= y.mean()
    den = np.sqrt(np.dot(x, x) * np.dot(y, y))
    return np.array([np.dot(x, y) / den if den > 0 else -np.inf, n])


def _overlap(shape, dy: int, dx: int):
    h, w = shape
    return ((slice(max(0, -dy), min(h, h - dy)), slice(max(0, -dx), min(w, w - dx))),
            (slice(max(0, dy), min(h, h + dy)), slice(max(0, dx), min(w, w + dx))))


def _at_shift(a, ma, b, mb, dy: int, dx: int) -> np.ndarray:
    (ya, xa), (yb, xb) = _overlap(a.shape, dy, dx)
    return _moments(a[ya, xa], ma[ya, xa], b[yb, xb], mb[yb, xb])


def _all_shifts(a, ma, b, mb, span: int) -> tuple[np.ndarray, np.ndarray]:
    """Masked NCC and counts of ``b`` read at ``(y + dy, x + dx)`` against ``a`` for every
    ``|dy|, |dx| <= span`` ((2 span + 1)^2 arrays, index ``span + d``), by FFT (Padfield)."""
    from scipy import fft

    h, w = a.shape
    # no wrap-around within the span; padded on to a length whose factors are small (a
    # block 298 px wide would be transformed as 2 x 149, five times slower than 300)
    fh, fw = fft.next_fast_len(h + span, real=True), fft.next_fast_len(w + span, real=True)

    def spec(f):
        return fft.rfft2(f, (fh, fw))

    def corr(fa, fb):  # sum_y f(y) g(y + d) for every d
        c = fft.irfft2(np.conj(fa) * fb, (fh, fw))
        idx_y = np.arange(-span, span + 1) % fh
        idx_x = np.arange(-span, span + 1) % fw
        return c[np.ix_(idx_y, idx_x)]

    ma, mb = ma.astype(np.float64), mb.astype(np.float64)
    a, b = a.astype(np.float64) * ma, b.astype(np.float64) * mb
    fma, fmb, fa, fb = spec(ma), spec(mb), spec(a), spec(b)
    n = np.rint(corr(fma, fmb))
    sa, sb = corr(fa, fmb), corr(fma, fb)
    saa, sbb = corr(spec(a * a), fmb), corr(fma, spec(b * b))
    sab = corr(fa, fb)
    safe = np.maximum(n, 1)
    cov = sab - sa * sb / safe
    var = np.maximum(saa - sa * sa / safe, 0) * np.maximum(sbb - sb * sb / safe, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = np.where((n >= 2) & (var > 0), cov / np.sqrt(var), -np.inf)
    return ncc, n


def _least_move(ncc: np.ndarray, dy: np.ndarray, dx: np.ndarray) -> tuple[int, int]:
    """The shift of the smallest length whose correlation is within ``TIE_NCC`` of the best:
    where the scene cannot tell shifts apart (a ramp, a stripe: the aperture problem), no
    move is made up."""
    near = ncc >= ncc.max() - TIE_NCC
    length = np.where(near, np.abs(dy) + np.abs(dx), np.iinfo(np.int64).max)
    i = np.unravel_index(np.argmin(length), length.shape)
    return int(dy[i]), int(dx[i])


def _plane_shift(a, ma, b, mb) -> tuple[tuple[int, int], float] | None:
    """:func:`pair_shift` on compared planes and their masks (``_plane``)."""
    levels = [(a, ma, b, mb)]
    while max(levels[-1][0].shape) > _SEARCH_SIDE and min(levels[-1][0].shape) >= 32:
        la, lma, lb, lmb = levels[-1]
        levels.append((*_half(la, lma), *_half(lb, lmb)))
    top = levels[-1]
    span = max(1, min(top[0].shape) // 4)
    ncc, n = _all_shifts(*top, span)
    # a shift must compare at least a quarter of the pixels the zero shift does
    ncc = np.where(n >= max(MIN_PIXELS, 0.25 * n[span, span]), ncc, -np.inf)
    if not ncc.max() >= MIN_NCC:
        return None
    dy, dx = _least_move(ncc, *np.mgrid[-span:span + 1, -span:span + 1])
    score = float(ncc[dy + span, dx + span])
    for level in reversed(levels[:-1]):
        dy, dx = 2 * dy, 2 * dx
        ys, xs = np.mgrid[dy - 1:dy + 2, dx - 1:dx + 2]
        trials = np.array([_at_shift(*level, y, x)[0] for y, x in zip(ys.ravel(), xs.ravel(),
                                                                      strict=True)])
        dy, dx = _least_move(trials.reshape(3, 3), ys, xs)
        score = float(trials.max())
    return (dy, dx), float(score)


def pair_shift(longer: np.ndarray, shorter: np.ndarray) -> tuple[tuple[int, int], float] | None:
    """The whole-pixel shift ``(dy, dx)`` at which ``shorter`` shows what ``longer`` shows at
    ``(y, x)``: ``shorter[y + dy, x + dx]``, with its correlation (module Conventions); None
    when the link cannot be trusted."""
    a, ma = _plane(longer)
    b, mb = _plane(shorter)
    if a.shape != b.shape:
        raise InputError(f"images differ in size: {a.shape} and {b.shape}")
    return _plane_shift(a, ma, b, mb)


def _vertex(before: float, at: float, after: float) -> float:
    """Where the parabola through three correlations one pixel apart peaks, relative to the
    middle one (0 where the middle one is not a peak)."""
    curve = before - 2.0 * at + after
    if not (np.isfinite(curve) and curve < 0 and at >= before and at >= after):
        return 0.0
    return float(np.clip(0.5 * (before - after) / curve, -0.5, 0.5))


def _rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The rotation and translation that best carry points ``src`` onto ``dst`` (m x 2, x
    and y; least squares, closed form): (the 2 x 3 matrix, the angle, the residuals)."""
    ps, qs = src - src.mean(axis=0), dst - dst.mean(axis=0)
    angle = math.atan2(float(np.sum(ps[:, 0] * qs[:, 1] - ps[:, 1] * qs[:, 0])),
                       float(np.sum(ps[:, 0] * qs[:, 0] + ps[:, 1] * qs[:, 1])))
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    t = dst.mean(axis=0) - rot @ src.mean(axis=0)
    fit = np.hstack([rot, t[:, None]])
    return fit, angle, _misfit(fit, src, dst)


def _misfit(fit: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """How far (px) the 2 x 3 ``fit`` carries each point of ``src`` from its ``dst``."""
    return np.hypot(*(src @ fit[:, :2].T + fit[:, 2] - dst).T)


def _peak(block, dy: int, dx: int) -> tuple[int, int, dict]:
    """The whole-pixel shift of best correlation near ``(dy, dx)`` (steps to the best of the
    3 x 3 around it until it is that best) and the correlations of it and its four
    neighbours, which place the peak to a fraction of a pixel (:func:`_vertex`)."""
    ncc: dict = {}

    def at(y: int, x: int) -> float:
        if (y, x) not in ncc:
            ncc[y, x] = _at_shift(*block, y, x)[0]
        return ncc[y, x]
    for _ in range(8):
        best = max(((dy + u, dx + v) for u in (-1, 0, 1) for v in (-1, 0, 1)),
                   key=lambda d: (at(*d), -abs(d[0] - dy) - abs(d[1] - dx)))
        if best == (dy, dx):
            break
        dy, dx = best
    return dy, dx, {(u, v): at(dy + u, dx + v)
                    for u, v in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))}


def _link_turn(a, ma, b, mb, dy: int, dx: int) -> tuple[np.ndarray | None, bool]:
    """The turn of a link whose whole-pixel shift is ``(dy, dx)``: (the 2 x 3 matrix that
    carries ``(x, y, 1)`` of ``a`` to where ``b`` shows the same point, or None where the
    turn moves no pixel by more than ``TURN_PX`` or is not told; whether it was told: False
    where too few blocks agree or the turn is within three standard errors) (module
    Conventions, rotation)."""
    import cv2

    (ya, xa), _ = _overlap(a.shape, dy, dx)
    cell_h, cell_w = (ya.stop - ya.start) // _GRID, (xa.stop - xa.start) // _GRID
    side_h, side_w = min(cell_h, _BLOCK), min(cell_w, _BLOCK)
    if min(side_h, side_w) < _MIN_BLOCK:
        return None, True  # too small a frame for a turn to move a corner by much
    corners = [(ya.start + i * cell_h + (cell_h - side_h) // 2,
                xa.start + j * cell_w + (cell_w - side_w) // 2)
               for i in range(_GRID) for j in range(_GRID)]
    size = (a.shape[1], a.shape[0])
    half_diagonal = 0.5 * math.hypot(*a.shape)
    # bilinear reads of b: a pixel is compared when the four it blends are
    inner = cv2.erode(mb.astype(np.uint8), np.ones((3, 3), np.uint8))
    fit = None
    for _ in range(1 + _REFINE):
        if fit is None:  # b as stored, at the link's whole-pixel shift
            seen, seen_mask, (oy, ox) = b, mb, (dy, dx)
        else:  # b carried back by the fit so far: what is left is a fraction of a pixel
            back = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            seen = cv2.warpAffine(b, fit, size, flags=back)
            seen_mask = cv2.warpAffine(inner, fit, size,
                                       flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
            oy = ox = 0
        src, dst = [], []
        for y0, x0 in corners:
            at_a = (slice(y0, y0 + side_h), slice(x0, x0 + side_w))
            at_b = (slice(y0 + oy, y0 + oy + side_h), slice(x0 + ox, x0 + ox + side_w))
            block = (a[at_a], ma[at_a], seen[at_b], seen_mask[at_b])
            if fit is None:  # first, each block's whole-pixel shift
                found = _plane_shift(*block)
                if found is None:
                    continue
                fy, fx = found[0]
            else:  # then what is left, to a fraction of a pixel
                ly, lx, ncc = _peak(block, 0, 0)
                if not ncc[0, 0] >= MIN_NCC:
                    continue
                fy = ly + _vertex(ncc[-1, 0], ncc[0, 0], ncc[1, 0])
                fx = lx + _vertex(ncc[0, -1], ncc[0, 0], ncc[0, 1])
            cy, cx = y0 + (side_h - 1) / 2, x0 + (side_w - 1) / 2
            src.append((cx, cy))
            dst.append((cx + ox + fx, cy + oy + fy) if fit is None
                       else fit @ (cx + fx, cy + fy, 1.0))
        src_a, dst_a = np.array(src, np.float64), np.array(dst, np.float64)
        # whole-pixel shifts of turned blocks scatter by a pixel or two (a block sheared by
        # the turn has a broad peak): the first consensus is a coarse one
        tolerance = _FIT_PX if fit is not None else _COARSE_PX
        keep = _consensus(src_a, dst_a, tolerance) if len(src) >= _MIN_BLOCKS else None
        if keep is None:
            return None, False
        fit, angle, residual = _rigid_fit(src_a[keep], dst_a[keep])
        if abs(angle) * half_diagonal < 0.5 * TURN_PX:
            # far below a visible turn (on a tripod every block moves as the frame does, to
            # the whole pixel): no need to measure it finer
            return None, True
    inside = src_a[keep]
    lever = float(np.sum((inside - inside.mean(axis=0)) ** 2))
    error = math.sqrt(float(np.sum(residual ** 2)) / (2 * int(keep.sum()) - 3) / lever)
    if abs(angle) * half_diagonal <= TURN_PX:
        return None, True
    return (fit, True) if abs(angle) > 3.0 * error else (None, False)


def _consensus(src: np.ndarray, dst: np.ndarray, tolerance: float) -> np.ndarray | None:
    """The blocks that move as one rigid body: of the turns and translations that carry two
    blocks exactly, the one that carries most blocks within ``tolerance`` px (then the smallest
    summed residual), refitted to those blocks and its blocks taken again; None when fewer
    than ``_MIN_BLOCKS`` agree.  A block that moved otherwise (a subject that moved,
    parallax, a stripe whose own direction no shift can tell) is left out, however far off
    it is."""
    m = len(src)
    best, keep = None, None
    for i in range(m):
        for j in range(i + 1, m):
            fit, _, _ = _rigid_fit(src[[i, j]], dst[[i, j]])
            residual = _misfit(fit, src, dst)
            near = residual <= tolerance
            key = (int(near.sum()), -float(residual[near].sum()))
            if best is None or key > best:
                best, keep = key, near
    if keep is None or keep.sum() < _MIN_BLOCKS:
        return None
    fit, _, _ = _rigid_fit(src[keep], dst[keep])
    keep = _misfit(fit, src, dst) <= tolerance
    return keep if keep.sum() >= _MIN_BLOCKS else None


def _chain_window(maps: np.ndarray, shape: tuple[int, int]) -> list[int]:
    """The largest window ``[y0, y1] x [x0, x1]`` (inclusive) of the reference, shrunk side
    by side from the whole frame, whose every pixel each of ``maps`` (n x 2 x 3, reference
    ``(x, y, 1)`` to image ``(x, y)``) carries inside the image: an affine map carries a
    rectangle to a parallelogram, so its corners decide."""
    h, w = shape
    y0, y1, x0, x1 = 0, h - 1, 0, w - 1
    for _ in range(4 * (h + w)):
        inward = [0, 0, 0, 0]  # y0, y1, x0, x1
        for m in maps:
            for ys, xs, (y, x) in ((0, 2, (y0, x0)), (1, 2, (y1, x0)), (0, 3, (y0, x1)),
                                   (1, 3, (y1, x1))):
                px, py = m @ (x, y, 1.0)
                over = math.ceil(max(-px, px - (w - 1), -py, py - (h - 1)))
                if over > 0:
                    inward[ys], inward[xs] = max(inward[ys], over), max(inward[xs], over)
        if not any(inward) or y1 - y0 < 16 or x1 - x0 < 16:
            break
        y0, y1, x0, x1 = y0 + inward[0], y1 - inward[1], x0 + inward[2], x1 - inward[3]
    return [y0, y1, x0, x1]


def align_series(images: list[np.ndarray], exposures, turns: bool = True) -> Registration:
    """Register the images of an exposure series (``exposures``: their relative exposures,
    any consistent unit) to the middle exposure (module Conventions); ``turns``: also find
    the turn of each link (rotation).

    Returns a :class:`Registration`; crop each image with ``Registration.crop``."""
    n = len(images)
    order = np.argsort(np.asarray(exposures, np.float64))[::-1]  # longest first
    step = np.zeros((n, 2), np.int64)  # shift of order[k] against order[k - 1]
    links = [np.eye(3) for _ in range(n)]  # order[k - 1] (x, y, 1) to order[k]
    unregistered, untold, turned = [], [], False
    b, mb = _plane(images[order[0]])
    for k in range(1, n):
        # each frame is compared twice, as the shorter of one link and the longer of the next
        a, ma = b, mb
        b, mb = _plane(images[order[k]])
        if a.shape != b.shape:
            raise InputError(f"images differ in size: {a.shape} and {b.shape}")
        found = _plane_shift(a, ma, b, mb)
        if found is None:
            unregistered.append(int(order[k]))
            continue
        step[k] = found[0]
        links[k][:2, 2] = step[k][::-1]
        turn, told = _link_turn(a, ma, b, mb, *found[0]) if turns else (None, True)
        if not told:
            untold.append(int(order[k]))
        if turn is not None:
            links[k][:2] = turn
            turned = True
    h, w = images[0].shape[:2]
    if turned:
        return _turned(links, order, unregistered, untold, (h, w))
    chained = np.cumsum(step, axis=0)
    chained -= chained[n // 2]  # against the middle exposure
    shifts = np.zeros((n, 2), np.int64)
    shifts[order] = chained
    lo = np.maximum(-shifts.min(axis=0), 0)
    hi = np.array([h, w]) - np.maximum(shifts.max(axis=0), 0)
    need = min(MIN_OVERLAP, h, w)
    if shifts.any() and np.any(hi - lo < need):
        raise InputError(f"exposure series: the images overlap by less than {need} px after "
                         f"registration (shifts {shifts.tolist()}); are they of one scene?")
    window = (slice(int(lo[0]), int(hi[0])), slice(int(lo[1]), int(hi[1])))
    return Registration(shifts, window, int(order[n // 2]), tuple(sorted(unregistered)))


def _turned(links: list[np.ndarray], order: np.ndarray, unregistered: list[int],
            untold: list[int], shape: tuple[int, int]) -> Registration:
    """The registration of a series with a turned link: the links chained to the middle
    exposure as maps, the window every map keeps inside its image."""
    n = len(links)
    chained = [np.eye(3)]
    for k in range(1, n):
        chained.append(links[k] @ chained[-1])
    back = np.linalg.inv(chained[n // 2])
    maps = np.zeros((n, 2, 3))
    for k in range(n):
        m = (chained[k] @ back)[:2]
        whole = np.rint(m[:, 2])
        # a frame chained to the reference by whole-pixel shifts alone (its turns cancel to
        # rounding: the reference itself) is that shift exactly, so it is cropped, not read
        if np.abs(m[:, :2] - np.eye(2)).max() < 1e-12 and np.abs(m[:, 2] - whole).max() < 1e-9:
            m = np.hstack([np.eye(2), whole[:, None]])
        maps[order[k]] = m
    h, w = shape
    centre = np.array([(w - 1) / 2, (h - 1) / 2, 1.0])
    moved = maps @ centre - centre[:2]
    shifts = np.rint(moved[:, ::-1]).astype(np.int64)
    y0, y1, x0, x1 = _chain_window(maps, shape)
    need = (min(MIN_OVERLAP, h), min(MIN_OVERLAP, w))
    if y1 - y0 + 1 < need[0] or x1 - x0 + 1 < need[1]:
        raise InputError(f"exposure series: the images overlap by less than {need[0]} x "
                         f"{need[1]} px after registration; are they of one scene?")
    window = (slice(y0, y1 + 1), slice(x0, x1 + 1))
    return Registration(shifts, window, int(order[n // 2]), tuple(sorted(unregistered)), maps,
                        tuple(sorted(untold)))


def describe(registration: Registration, names: list[str]) -> dict:
    """The registration as a report records it: each image's shift (rows, cols) against the
    reference, the common window the images were cropped to, the links not trusted and
    :func:`summary`'s line."""
    zero = [n for i, (n, s) in enumerate(zip(names, registration.shifts, strict=True))
            if not s.any() and not round(registration.turn_degrees(i), 4)]
    rows, cols = registration.window
    turns = {} if registration.maps is None else {
        "turns_deg": {n: round(registration.turn_degrees(i), 4) for i, n in enumerate(names)},
        "turn_untold": [names[i] for i in registration.untold]}
    return {"reference": names[registration.reference],
            "shifts": {n: [int(v) for v in s]
                       for n, s in zip(names, registration.shifts, strict=True)},
            "unshifted": zero,
            "window": {"rows": [rows.start, rows.stop], "cols": [cols.start, cols.stop]},
            "unregistered": [names[i] for i in registration.unregistered],
            **turns,
            "summary": summary(registration, names)}


def summary(registration: Registration, names: list[str]) -> str:
    """One line for a terminal or a report: what moved, the window kept, what could not be
    registered."""
    moved = []
    for i, (n, s) in enumerate(zip(names, registration.shifts, strict=True)):
        turn = round(registration.turn_degrees(i), 2)  # a chain of turns that cancel: 1e-15
        if s.any() or turn:
            moved.append(f"{n} ({int(s[0])}, {int(s[1])})"
                         + (f" turned {turn:+.2f} deg" if turn else ""))
    rows, cols = registration.window
    found = (f"{', '.join(moved)} px (rows, cols) against "
             f"{names[registration.reference]}")
    if not moved:
        text = "registered: no shift between the images"
    else:
        text = (f"registered: {found}; cropped to {cols.stop - cols.start} x "
                f"{rows.stop - rows.start} (W x H)")
    if registration.maps is not None and registration.untold:
        text += ("; turn not told (too few unclipped blocks agree on one with the next "
                 "longer exposure, taken as none): "
                 f"{', '.join(names[i] for i in registration.untold)}")
    if registration.unregistered:
        text += ("; not registered (too little unclipped overlap with the next longer "
                 f"exposure, taken as unshifted): "
                 f"{', '.join(names[i] for i in registration.unregistered)}")
    return text
