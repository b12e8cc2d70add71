"""Deep-sea lighting compensation by pixel-wise medians (arXiv 2110.00480), METHODS.md section 5.

Image model ``I_c = A_s F + B`` per channel:

- ``B`` (backscatter) = pixel-wise median of water-only frames;
- ``M_t`` = pixel-wise median of a centred window of ``n`` seafloor frames (the window shifts
  to stay full near the ends of the sequence);
- ``F_t = (M_t - B) / A_ref`` with ``A_ref`` the per-channel median of ``(M - B)`` over the
  first window unless given (fixed for the whole sequence so frames stay comparable);
- ``A_t = (I_t - B) / max(F_t, eps)``; pixels with ``F_t < eps`` are reported invalid.

:class:`UnderwaterCompensator` streams the sequence through a ring buffer of ``n`` frames,
so memory does not grow with its length. For integer frames the window median is an exact
radix selection in a numba kernel (8 or 16 passes of counting per pixel, one thread per core);
float frames use ``numpy.partition``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator

import numpy as np

from ..errors import ParameterError
from ..validate import (
    check_all_finite,
    check_dtype,
    check_int_range,
    check_nonempty,
    check_odd,
    check_positive,
    check_probability,
    check_shape,
)

__all__ = ["UnderwaterCompensator", "gray_world", "median_failure_probability", "window_median"]

_MAX_WINDOW = 65535  # the kernel counts in uint16


def median_failure_probability(n: int, c: float) -> float:
    """Probability that an ``n``-sample median is corrupted by outliers of rate ``c``.

    ``P_fail = sum_{u=ceil(n/2)}^{n} C(n, u) c^u (1 - c)^(n - u)``: at least half the samples
    are outliers (METHODS.md section 5).

    Parameters
    ----------
    n : int
        Window size, >= 1.
    c : float
        Contamination probability of one sample, in [0, 1].

    Returns
    -------
    float
    """
    from scipy import stats

    n = check_int_range(n, "n", low=1)  # window size
    check_probability(c, "c", open_low=False)  # contamination
    first = math.ceil(n / 2)
    # sf(k) = P(X > k) = P(X >= k + 1)
    return float(stats.binom.sf(first - 1, n, c))


def _rank_select(buf: np.ndarray, rank: int, *, parallel: bool = True) -> np.ndarray:
    """``rank``-th smallest along axis 0 of an (n, P) array (exact)."""
    if buf.dtype in (np.uint8, np.uint16) and buf.shape[0] <= _MAX_WINDOW:
        from . import _underwater_kernels as kern

        out = np.empty(buf.shape[1], buf.dtype)
        nbits = 8 * buf.dtype.itemsize
        kern.run_split(kern.select_rank, buf.shape[1], (buf, rank, nbits, out), parallel=parallel)
        return out
    out = np.empty(buf.shape[1], buf.dtype)
    step = 1 << 16  # bound the temporary copy numpy.partition makes
    for a in range(0, buf.shape[1], step):
        out[a : a + step] = np.partition(buf[:, a : a + step], rank, axis=0)[rank]
    return out


def window_median(frames: np.ndarray, *, parallel: bool = True) -> np.ndarray:
    """Pixel-wise median over axis 0, as ``numpy.median`` (mean of the middle pair when even).

    Parameters
    ----------
    frames : (n, ...) uint8, uint16 or float array
    parallel : bool
        Split integer frames over one thread per core.

    Returns
    -------
    float32 array of shape ``frames.shape[1:]``
    """
    a = np.asarray(frames)
    check_shape(a, "(N, P, ...)", "frames")
    check_nonempty(a, "frames")
    if a.dtype not in (np.uint8, np.uint16):
        a = a.astype(np.float32)
        check_all_finite(a, "frames")
    flat = np.ascontiguousarray(a.reshape(a.shape[0], -1))
    n = flat.shape[0]
    hi = _rank_select(flat, n // 2, parallel=parallel).astype(np.float32)
    if n % 2 == 0:
        hi += _rank_select(flat, n // 2 - 1, parallel=parallel).astype(np.float32)
        hi *= 0.5
    return hi.reshape(a.shape[1:])


def gray_world(image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Gray-world white balance: scale each channel so its mean equals the mean over channels.

    Parameters
    ----------
    image : (H, W, 3) float
    valid : (H, W) bool, optional
        Pixels used for the means (default all).
    """
    img = np.asarray(image, np.float32)
    check_shape(img, "(H, W, C)", "image")
    if valid is not None:
        valid = np.asarray(valid)
        check_shape(valid, "({}, {})".format(*img.shape[:2]), "valid")
        check_dtype(valid, "valid", (np.bool_,))
    px = img[valid] if valid is not None else img.reshape(-1, img.shape[-1])
    if px.size == 0:
        return img.copy()
    means = px.mean(axis=0, dtype=np.float64)
    gains = np.where(means > 0, means.mean() / np.where(means > 0, means, 1), 1.0)
    return img * gains.astype(np.float32)


def _check_settings(window, eps) -> None:
    check_odd(window, "window", low=1, high=_MAX_WINDOW)
    check_positive(eps, "eps")


def _as_frame(frame, shape: tuple | None, name: str) -> np.ndarray:
    """``frame`` as (H, W, C), a number type; of ``shape`` when given."""
    f = np.asarray(frame)
    if f.ndim == 2:
        f = f[:, :, None]
    check_shape(f, "(H, W, C)" if shape is None else "({}, {}, {})".format(*shape), name)
    check_dtype(f, name, "uif")
    return f


class UnderwaterCompensator:
    """Streaming median lighting compensation of a seafloor image sequence.

    Parameters
    ----------
    water_frames : iterable of (H, W, C) arrays, or an (N, H, W, C) array
        Water-only frames (no seafloor in view); their pixel-wise median is the
        backscatter ``B``. All are held once to take the median.
    window : int
        Odd number ``n`` of seafloor frames in each median window (default 31).
    a_ref : float or sequence of C floats, optional
        Reference albedo ``A_ref`` per channel, in image units. Default: per-channel median of
        ``M - B`` over the first window used (the sequence's first), kept for the whole
        sequence.
    eps : float
        Lower bound of the factor image ``F``; pixels with ``F < eps`` are invalid.
    white_balance : bool
        Gray-world white balance of each corrected frame (over its valid pixels).
    parallel : bool
        Use one thread per core (threads live only during a call, so forking is safe).

    Attributes
    ----------
    backscatter : (H, W, C) float32
        ``B``.
    a_ref : (C,) float32 or None
        Reference albedo in use (set after the first window when not given).
    buffered : int
        Frames currently held in the ring buffer (never more than ``window``).

    Examples
    --------
    >>> comp = UnderwaterCompensator(water, window=31)
    >>> for albedo, valid in comp.process(frame_iterator):
    ...     ...
    """

    def __init__(
        self,
        water_frames: Iterable[np.ndarray] | np.ndarray,
        *,
        window: int = 31,
        a_ref: float | Iterable[float] | None = None,
        eps: float = 1e-3,
        white_balance: bool = False,
        parallel: bool = True,
    ) -> None:
        _check_settings(window, eps)
        water = [_as_frame(f, None, f"water_frames[{i}]") for i, f in enumerate(water_frames)]
        if not water:
            raise ParameterError(
                "no water-only frames: the backscatter B cannot be estimated", param="water_frames"
            )
        for i, f in enumerate(water):
            _as_frame(f, water[0].shape, f"water_frames[{i}]")
        if len({f.dtype for f in water}) == 1:
            stack = np.stack(water)
        else:
            stack = np.stack([f.astype(np.float32) for f in water])
        del water
        self.parallel = bool(parallel)
        self._setup(window_median(stack, parallel=self.parallel), window, a_ref, eps, white_balance)

    @classmethod
    def from_backscatter(
        cls,
        backscatter: np.ndarray,
        *,
        window: int = 31,
        a_ref: float | Iterable[float] | None = None,
        eps: float = 1e-3,
        white_balance: bool = False,
        parallel: bool = True,
    ) -> UnderwaterCompensator:
        """A compensator with a known backscatter ``B`` ((H, W, C) float, image units).

        Used to split one sequence into segments processed in parallel: ``B`` and ``A_ref``
        are computed once and shared, so every segment gives the bytes a single pass would.
        """
        obj = cls.__new__(cls)
        obj.parallel = bool(parallel)
        b = np.asarray(backscatter, dtype=np.float32)
        if b.ndim == 2:
            b = b[:, :, None]
        check_shape(b, "(H, W, C)", "backscatter")
        check_all_finite(b, "backscatter")
        obj._setup(b, window, a_ref, eps, white_balance)
        return obj

    def _setup(self, backscatter, window, a_ref, eps, white_balance) -> None:
        _check_settings(window, eps)
        self.window = int(window)
        self.eps = float(eps)
        self.white_balance = bool(white_balance)
        self.backscatter = backscatter
        self._flat_b = np.ascontiguousarray(backscatter, dtype=np.float32).reshape(-1)
        self.shape = backscatter.shape
        if a_ref is not None:
            a = np.atleast_1d(np.asarray(a_ref, dtype=np.float32))
            if a.size == 1:
                a = np.repeat(a, self.shape[2])
            if a.shape != (self.shape[2],) or not np.all(np.isfinite(a)) or np.any(a <= 0):
                raise ParameterError(
                    f"a_ref must be one positive value or {self.shape[2]}, got {a_ref}"
                )
            self.a_ref = a
        else:
            self.a_ref = None
        self.buffered = 0

    # ------------------------------------------------------------------ internals

    def _median(self, buf: np.ndarray) -> np.ndarray:
        """Window median, flat, in the buffer's dtype (exact for integers)."""
        return _rank_select(buf, self.window // 2, parallel=self.parallel)

    def reference_albedo(self, median: np.ndarray) -> np.ndarray:
        """Per-channel median of ``median - B`` over the image: the default ``A_ref``.

        Parameters
        ----------
        median : (H, W, C) float
            A window median ``M``.

        Returns
        -------
        (C,) float32, all > 0
        """
        median = np.asarray(median, np.float32)
        check_shape(median, "({}, {}, {})".format(*self.shape), "median")
        signal = median - self.backscatter
        # One contiguous channel at a time: numpy.median of a 1-D array is a quick select.
        a = np.array(
            [np.median(np.ascontiguousarray(signal[..., c]).ravel()) for c in range(self.shape[2])],
            dtype=np.float32,
        )
        if np.any(a <= 0):
            raise ParameterError(
                f"the median of (M - B) is not positive (A_ref = {a.tolist()}): the water-only "
                "frames are as bright as the seafloor; check them or pass a_ref"
            )
        return a

    def first_window_median(self, frames: Iterable[np.ndarray]) -> np.ndarray:
        """Median ``M`` of the first ``window`` frames of ``frames`` ((H, W, C) float32)."""
        stack = []
        for i, f in enumerate(frames):
            stack.append(_as_frame(f, self.shape, f"frames[{i}]"))
            if len(stack) == self.window:
                break
        if len(stack) < self.window:
            raise ParameterError(
                f"only {len(stack)} seafloor frame(s), fewer than the median window of "
                f"{self.window}"
            )
        return window_median(np.stack(stack), parallel=self.parallel)

    def _correct(self, frame: np.ndarray, median: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Correct one flat frame with a flat window median: (albedo (H, W, C), valid (H, W))."""
        from . import _underwater_kernels as kern

        if self.a_ref is None:
            self.a_ref = self.reference_albedo(median.reshape(self.shape))
        h, w, c = self.shape
        albedo = np.empty(h * w * c, np.float32)
        valid = np.empty(h * w, np.bool_)
        args = (frame, median, self._flat_b, self.a_ref, np.float32(self.eps), albedo, valid)
        kern.run_split(kern.compensate, h * w, args, parallel=self.parallel)
        albedo = albedo.reshape(self.shape)
        valid = valid.reshape(h, w)
        if self.white_balance:
            albedo = gray_world(albedo, valid)
        return albedo, valid

    # ------------------------------------------------------------------ public

    def process(
        self, frames: Iterable[np.ndarray], *, emit: tuple[int, int] | None = None
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Correct a sequence of seafloor frames, lazily.

        Parameters
        ----------
        frames : iterable of (H, W, C) arrays
            Consumed one at a time (a generator reading files is fine); at most ``window``
            are held. It must yield at least ``window`` frames.
        emit : (start, stop), optional
            Only correct (and yield) frames ``start <= t < stop`` of this sequence (the others
            still feed the windows). Used to split a long sequence into segments.

        Yields
        ------
        albedo : (H, W, C) float32
            ``A_t`` in image units (relative to ``A_ref``).
        valid : (H, W) bool
            False where ``F_t < eps`` in any channel.
        """
        n = self.window
        h = n // 2
        lo, hi = (0, math.inf) if emit is None else emit
        P = int(np.prod(self.shape))
        buf = None
        slot_of = {}  # frame index -> ring slot, for the frames still in the buffer
        it = iter(frames)
        t_in = 0
        self.buffered = 0
        dtype = None

        def check(f, t):
            nonlocal dtype
            f = _as_frame(f, self.shape, f"frames[{t}]")
            dtype = f.dtype if dtype is None else dtype
            if f.dtype != dtype:
                raise ParameterError(f"frame {t} is {f.dtype}, the sequence started as {dtype}")
            check_all_finite(f, f"frames[{t}]")
            return f

        try:
            # Fill the first window.
            for f in it:
                f = check(f, t_in)
                if buf is None:
                    buf = np.empty(
                        (n, P), f.dtype if f.dtype in (np.uint8, np.uint16) else np.float32
                    )
                buf[t_in % n] = f.reshape(-1)
                slot_of[t_in] = t_in % n
                t_in += 1
                self.buffered = min(t_in, n)
                if t_in == n:
                    break
            if t_in < n:
                raise ParameterError(
                    f"only {t_in} seafloor frame(s), fewer than the median window of {n}"
                )
            median = None
            # Frames 0..h use the first window.
            for t in range(h + 1):
                if lo <= t < hi:
                    median = self._median(buf) if median is None else median
                    yield self._correct(buf[slot_of[t]], median)
            t_out = h + 1
            for f in it:
                f = check(f, t_in)
                slot = t_in % n  # the oldest frame (t_in - n) leaves the buffer
                slot_of.pop(t_in - n, None)
                buf[slot] = f.reshape(-1)
                slot_of[t_in] = slot
                t_in += 1
                if lo <= t_out < hi:
                    median = self._median(buf)
                    yield self._correct(buf[slot_of[t_out]], median)
                else:
                    median = None
                t_out += 1
            # The last h frames share the last (full) window.
            median = None
            for t in range(t_out, t_in):
                if lo <= t < hi:
                    median = self._median(buf) if median is None else median
                    yield self._correct(buf[slot_of[t]], median)
        finally:
            self.buffered = 0
