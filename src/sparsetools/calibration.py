"""The camera + sensor calibration type shared by every command.

Conventions (METHODS.md section 0): camera frame x right, y down, z forward; pixel
centres at integer coordinates; depth is camera z in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import CalibrationError, ParameterError

__all__ = ["Calibration", "crop_intrinsics", "resize_intrinsics", "resize_intrinsics_xy"]


def resize_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """Intrinsics after resizing the image by ``scale``.

    Parameters
    ----------
    K : (3, 3) or (3, 4) array
        Intrinsic matrix (a KITTI ``P`` matrix is accepted; its translation column is scaled too).
    scale : float
        Resize factor, > 0.

    Returns
    -------
    (3, 3) or (3, 4) float64
        ``f' = s f`` and ``c' = s (c + 0.5) - 0.5`` (pixel centres at integers).
    """
    if not np.isfinite(scale) or scale <= 0:
        raise ParameterError(f"resize factor must be > 0, got {scale}")
    return resize_intrinsics_xy(K, scale, scale)


def resize_intrinsics_xy(K: np.ndarray, scale_x: float, scale_y: float) -> np.ndarray:
    """Intrinsics after resizing the image by ``scale_x`` across and ``scale_y`` down.

    Parameters
    ----------
    K : (3, 3) or (3, 4) array
        Intrinsic matrix (a KITTI ``P`` matrix is accepted; its translation column is scaled too).
    scale_x, scale_y : float
        Resize factors of the columns and the rows, > 0 (``W' / W`` and ``H' / H``).

    Returns
    -------
    (3, 3) or (3, 4) float64
        ``fx' = sx fx``, ``cx' = sx (cx + 0.5) - 0.5``, the same for y with ``sy``.
    """
    for name, s in (("horizontal", scale_x), ("vertical", scale_y)):
        if not np.isfinite(s) or s <= 0:
            raise ParameterError(f"{name} resize factor must be > 0, got {s}")
    # Pixel centres sit at integers, so the grid maps as u' = s (u + 0.5) - 0.5. Written as a
    # left product it also handles a KITTI P whose third row carries a translation.
    A = np.array([[scale_x, 0.0, 0.5 * scale_x - 0.5],
                  [0.0, scale_y, 0.5 * scale_y - 0.5],
                  [0.0, 0.0, 1.0]])  # fmt: skip
    return A @ np.asarray(K, dtype=np.float64)


def crop_intrinsics(K: np.ndarray, top: int, left: int) -> np.ndarray:
    """Intrinsics after cropping ``top`` rows and ``left`` columns off the image."""
    # A left product with a pixel translation also handles a KITTI 3x4 P exactly.
    shift = np.array([[1.0, 0.0, -left], [0.0, 1.0, -top], [0.0, 0.0, 1.0]])
    return shift @ np.asarray(K, dtype=np.float64)


#: Largest deviation of ``R^T R`` from the identity accepted in a sensor-to-camera rotation
#: (KITTI's files, printed with 6-9 digits, are orthonormal to ~1e-6).
RIGID_TOLERANCE = 1e-4


@dataclass(frozen=True)
class Calibration:
    """Pinhole camera with the rigid transform from a depth sensor (LiDAR, radar) to it.

    Attributes
    ----------
    K : (3, 3) float64
        Camera intrinsics in pixels.
    T_cam_from_sensor : (4, 4) float64
        Rigid transform taking sensor coordinates (metres) to camera coordinates.
    width, height : int or None
        Image size in pixels (None when the calibration file does not say).
    P : (3, 4) float64 or None
        Full KITTI projection matrix when known. KITTI's ``P2`` has a small translation
        column (the offset of camera 2 from the reference camera); projection uses
        ``P @ T_cam_from_sensor`` as KITTI and monodepth2 do, so that column is kept.
    source : str
        Where the calibration came from (for messages and manifests).
    """

    K: np.ndarray
    T_cam_from_sensor: np.ndarray
    width: int | None = None
    height: int | None = None
    P: np.ndarray | None = None
    source: str = ""
    extra: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        T = np.asarray(self.T_cam_from_sensor, dtype=np.float64)
        where = f" in {self.source}" if self.source else ""
        if K.shape != (3, 3):
            raise CalibrationError(f"intrinsics K must be 3x3, got shape {K.shape}{where}")
        if T.shape != (4, 4):
            raise CalibrationError(f"T_cam_from_sensor must be 4x4, got shape {T.shape}{where}")
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(T))):
            raise CalibrationError(f"calibration holds non-finite values{where}")
        if abs(np.linalg.det(K)) < 1e-9 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(
                f"intrinsics K are singular or have a non-positive focal length{where}"
            )
        if abs(np.linalg.det(T[:3, :3])) < 1e-9:
            raise CalibrationError(f"T_cam_from_sensor has a singular rotation{where}")
        if np.max(np.abs(T[3] - (0.0, 0.0, 0.0, 1.0))) > 1e-9:
            raise CalibrationError(
                f"T_cam_from_sensor is not a rigid transform: its bottom row is "
                f"{np.array2string(T[3], precision=4)}, not [0 0 0 1]{where}"
            )
        R = T[:3, :3]
        err = float(np.max(np.abs(R.T @ R - np.eye(3))))
        if err > RIGID_TOLERANCE or np.linalg.det(R) < 0:
            raise CalibrationError(
                "T_cam_from_sensor is not a rigid transform: its 3x3 part is not a rotation "
                f"(max |R^T R - I| = {err:.3g}, det {np.linalg.det(R):.4g}; a scaled R0_rect?)"
                f"{where}"
            )
        P = None
        if self.P is not None:
            P = np.asarray(self.P, dtype=np.float64)
            if P.shape != (3, 4) or not np.all(np.isfinite(P)):
                raise CalibrationError(f"projection matrix P must be a finite 3x4{where}")
            if abs(np.linalg.det(P[:, :3])) < 1e-9:
                raise CalibrationError(f"projection matrix P is singular{where}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if value is not None and (int(value) != value or value <= 0):
                raise CalibrationError(f"image {name} must be a positive integer{where}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_cam_from_sensor", T)
        object.__setattr__(self, "P", P)
        if self.width is not None:
            object.__setattr__(self, "width", int(self.width))
        if self.height is not None:
            object.__setattr__(self, "height", int(self.height))

    # -- derived quantities -------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels; raises when the calibration does not know it."""
        if self.width is None or self.height is None:
            raise ParameterError(
                "image size unknown: give --image-size WxH or --image IMG"
                + (f" (calibration {self.source} has none)" if self.source else "")
            )
        return self.width, self.height

    @property
    def projection(self) -> np.ndarray:
        """(3, 4) matrix taking homogeneous sensor points to homogeneous pixels."""
        P = self.P if self.P is not None else np.hstack([self.K, np.zeros((3, 1))])
        return P @ self.T_cam_from_sensor

    # -- edits ---------------------------------------------------------------------------------
    def with_size(self, width: int, height: int) -> Calibration:
        """The same calibration for an image of ``width`` x ``height`` pixels."""
        return replace(self, width=int(width), height=int(height))

    def for_size(self, width: int, height: int, *, given_by: str = "the image") -> Calibration:
        """:meth:`with_size`, refusing a size that contradicts the calibration's own.

        A calibration that knows its image size (KITTI raw ``S_rect``, a JSON ``width`` /
        ``height``, nuScenes) has intrinsics for that size only: another size would keep the
        principal point of the first and misplace every point.
        """
        if self.width is not None and self.height is not None:
            if (self.width, self.height) != (int(width), int(height)):
                raise CalibrationError(
                    f"{given_by} says {int(width)}x{int(height)} but the calibration "
                    f"{self.source or ''} is for {self.width}x{self.height} images: its "
                    "intrinsics do not fit (scale them with --resize instead)"
                )
            return self
        return self.with_size(width, height)

    def resized(self, scale: float) -> Calibration:
        """Calibration of the image resized by ``scale`` (METHODS.md section 0).

        The new size is ``round(scale * width)`` x ``round(scale * height)``.
        """
        K = resize_intrinsics(self.K, scale)
        P = resize_intrinsics(self.P, scale) if self.P is not None else None
        w = None if self.width is None else max(1, round(self.width * scale))
        h = None if self.height is None else max(1, round(self.height * scale))
        return replace(self, K=K, P=P, width=w, height=h)

    def resized_to(self, width: int, height: int) -> Calibration:
        """Calibration of the image resized to exactly ``width`` x ``height`` pixels.

        Each axis scales by its own factor, ``sx = width / self.width`` and
        ``sy = height / self.height`` (:func:`resize_intrinsics_xy`): an aspect ratio that
        changes (monodepth2's 640x192 from KITTI's 1242x375) changes ``fx / fy``.

        Raises
        ------
        ParameterError
            A size that is not two positive integers, or a calibration without a size.
        """
        for name, v in (("width", width), ("height", height)):
            if isinstance(v, bool) or int(v) != v or v <= 0:
                raise ParameterError(f"resize {name} must be a positive integer, got {v!r}")
        w0, h0 = self.size
        sx, sy = int(width) / w0, int(height) / h0
        K = resize_intrinsics_xy(self.K, sx, sy)
        P = resize_intrinsics_xy(self.P, sx, sy) if self.P is not None else None
        return replace(self, K=K, P=P, width=int(width), height=int(height))

    def cropped(self, top: int, left: int, height: int, width: int) -> Calibration:
        """Calibration of the crop of ``height`` x ``width`` pixels at (``top``, ``left``)."""
        if top < 0 or left < 0 or height <= 0 or width <= 0:
            raise ParameterError(
                f"crop must have top, left >= 0 and height, width > 0, got "
                f"top={top} left={left} height={height} width={width}"
            )
        if self.width is not None and self.height is not None:
            if left + width > self.width or top + height > self.height:
                raise ParameterError(
                    f"crop {width}x{height} at (left={left}, top={top}) does not fit the "
                    f"{self.width}x{self.height} image"
                )
        K = crop_intrinsics(self.K, top, left)
        P = crop_intrinsics(self.P, top, left) if self.P is not None else None
        return replace(self, K=K, P=P, width=int(width), height=int(height))

    def to_dict(self) -> dict:
        """JSON-serialisable form (the format :func:`sparsetools.io.calib.read_json_calib` reads)."""
        d = {
            "K": self.K.tolist(),
            "T_cam_from_sensor": self.T_cam_from_sensor.tolist(),
            "width": self.width,
            "height": self.height,
        }
        if self.P is not None:
            d["P"] = self.P.tolist()
        return d
