"""RGB images and KITTI-convention depth PNGs (OpenCV codecs, size checked before decoding)."""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError
from .atomic import atomic_write_bytes

__all__ = [
    "DEPTH_SCALE",
    "MAX_IMAGE_PIXELS",
    "check_pixel_count",
    "decode_depth_png",
    "decode_image_bytes",
    "encode_depth_png",
    "image_header_size",
    "image_size_of",
    "imdecode_captured",
    "import_cv2",
    "max_image_pixels",
    "read_depth_png",
    "read_image",
    "write_depth_png",
    "write_image",
]

log = logging.getLogger(__name__)

#: KITTI depth PNG: stored value = depth [m] * 256; 0 = no measurement.
DEPTH_SCALE = 256.0
#: Default limit: refuse to decode images declaring more pixels than this (decompression
#: bombs). ``SPARSETOOLS_MAX_IMAGE_PIXELS`` (a positive integer) replaces it.
MAX_IMAGE_PIXELS = 16384 * 16384 // 2


def max_image_pixels() -> int:
    """The pixel limit in force: ``SPARSETOOLS_MAX_IMAGE_PIXELS`` when set, else the default.

    Raises
    ------
    ParameterError
        The variable is set to something other than a positive integer.
    """
    text = os.environ.get("SPARSETOOLS_MAX_IMAGE_PIXELS")
    if text is None or not text.strip():
        return MAX_IMAGE_PIXELS
    try:
        value = int(text.strip())
    except ValueError:
        value = 0
    if value <= 0:
        raise ParameterError(
            f"SPARSETOOLS_MAX_IMAGE_PIXELS must be a positive integer, got {text!r}"
        )
    return value


def check_pixel_count(width: int, height: int, what: str) -> None:
    """Refuse an image or map size above :data:`MAX_IMAGE_PIXELS` (before allocating it).

    Raises
    ------
    FormatError
        ``what`` ("depth map", "<file>: declared size") names the culprit in the message.
    """
    limit = max_image_pixels()
    if int(width) * int(height) > limit:
        raise FormatError(
            f"{what} is {width}x{height} pixels, above the limit of {limit} "
            "(set SPARSETOOLS_MAX_IMAGE_PIXELS to raise it)"
        )


def image_header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) declared by a PNG or JPEG header, without decoding; None if unknown."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    if data[:2] == b"\xff\xd8":
        i = 2
        n = len(data)
        while i + 9 < n:
            if data[i] != 0xFF:
                i += 1
                continue
            marker = data[i + 1]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
                i += 1 if marker == 0xFF else 2
                continue
            seg_len = struct.unpack(">H", data[i + 2 : i + 4])[0]
            # SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC) carry the frame size.
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                h, w = struct.unpack(">HH", data[i + 5 : i + 9])
                return int(w), int(h)
            i += 2 + seg_len
    return None


def image_size_of(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of a PNG or JPEG from its header, without decoding the pixels.

    Raises
    ------
    FormatError
        Missing file, or a header that is neither PNG nor JPEG.
    """
    path = Path(path)
    try:
        with _open_regular(path, "image") as fh:
            head = fh.read(1 << 16)
            size = image_header_size(head)
            if size is None and head[:2] == b"\xff\xd8":
                # A JPEG's frame header can follow a large EXIF block.
                size = image_header_size(head + fh.read(MAX_IMAGE_FILE_BYTES))
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such image") from exc
    except IsADirectoryError as exc:
        raise FormatError(f"{path}: is a folder, expected an image") from exc
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if size is None or size[0] <= 0 or size[1] <= 0:
        raise FormatError(f"{path}: not a PNG or JPEG image (cannot read its size)")
    check_pixel_count(*size, f"{path}: declared size")
    return size


#: Largest image file read (bytes): a PNG at the default pixel limit stored uncompressed in
#: 16-bit RGBA is about 1 GiB.
MAX_IMAGE_FILE_BYTES = 4 << 30


def _open_regular(path: Path, what: str):
    """``path`` opened for reading when it is a regular file: a FIFO would block the open (it
    is opened without blocking), a device such as ``/dev/zero`` would be read forever."""
    import stat

    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    fh = os.fdopen(fd, "rb")
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        fh.close()
        if stat.S_ISDIR(mode):
            raise IsADirectoryError(f"{path} is a folder")
        raise FormatError(f"{path}: not a regular file (a device or a pipe?), expected a {what}")
    return fh


def _read_bytes(path: Path, what: str) -> bytes:
    article = "an" if what[:1] in "aeiou" else "a"
    try:
        with _open_regular(path, what) as fh:
            data = fh.read(MAX_IMAGE_FILE_BYTES + 1)
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such {what}") from exc
    except IsADirectoryError as exc:
        raise FormatError(f"{path}: is a folder, expected {article} {what}") from exc
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if not data:
        raise FormatError(f"{path}: empty file, expected {article} {what}")
    if len(data) > MAX_IMAGE_FILE_BYTES:
        raise FormatError(f"{path}: more than {MAX_IMAGE_FILE_BYTES} bytes, too large for {article} "
                          f"{what}")  # fmt: skip
    return data


_CV2_QUIET = False


def import_cv2():
    """Import OpenCV with its own log output limited to errors.

    OpenCV's decoders print warnings ("PNG input buffer is incomplete") on stderr for every
    corrupt file; the readers here raise :class:`FormatError` instead, and the command line
    promises one error line.
    """
    global _CV2_QUIET
    import cv2

    if not _CV2_QUIET:
        try:
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        except AttributeError:  # pragma: no cover - builds without the logging module
            pass
        _CV2_QUIET = True
    return cv2


def decode_image_bytes(data: bytes, *, source, what: str = "image", flags: int | None = None):
    """Decode PNG/JPEG bytes as stored (``cv2.IMREAD_UNCHANGED`` unless ``flags``), after
    checking the declared size against the pixel limit (decompression bombs).

    Raises
    ------
    FormatError
        Empty data, a size above the limit, or bytes that do not decode.
    """
    if not data:
        raise FormatError(f"{source}: empty data, expected a {what}")
    size = image_header_size(data)
    if size is not None:
        check_pixel_count(*size, f"{source}: declared size")
    if flags is None:
        flags = import_cv2().IMREAD_UNCHANGED
    img, detail = imdecode_captured(data, flags, source=str(source))
    if img is None:
        why = f": {detail}" if detail else ""
        raise FormatError(f"{source}: cannot decode {what} (corrupt or unsupported format){why}")
    return img


def _decode(data: bytes, path: Path, what: str, flags: int) -> np.ndarray:
    return decode_image_bytes(data, source=path, what=what, flags=flags)


def imdecode_captured(data: bytes, flags: int, *, source: str) -> tuple[np.ndarray | None, str]:
    """``cv2.imdecode`` with what libpng/libjpeg print on stderr captured.

    Returns the image (None when it cannot be decoded) and the libraries' text; when the
    image decoded after all, that text is logged as a warning naming ``source``.
    """
    from ._native import native_stderr_captured

    cv2 = import_cv2()
    with native_stderr_captured() as native:
        try:
            img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
        except cv2.error:  # OpenCV raises for some malformed headers instead of returning None
            img = None
    detail = native[0] if native else ""
    if img is not None and detail:
        log.warning("%s: %s", source, detail)
    return img, detail


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG/JPEG colour image.

    Returns
    -------
    (H, W, 3) uint8
        RGB (not OpenCV's BGR). Grey images are replicated to three channels; 16-bit
        images are refused (they are usually depth maps given in the wrong place).
    """
    import cv2

    path = Path(path)
    img = _decode(_read_bytes(path, "image"), path, "image", cv2.IMREAD_UNCHANGED)
    if img.dtype != np.uint8:
        raise FormatError(f"{path}: {img.dtype} image, expected 8-bit RGB (is this a depth map?)")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        img = img[:, :, :3]
    elif img.shape[2] != 3:
        raise FormatError(f"{path}: {img.shape[2]}-channel image, expected RGB")
    return np.ascontiguousarray(img[:, :, ::-1])


def write_image(path: str | os.PathLike, rgb: np.ndarray, *, overwrite: bool = True) -> None:
    """Write an (H, W, 3) uint8 RGB image (PNG or JPEG by suffix), atomically."""
    import cv2

    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ParameterError(f"expected (H, W, 3) uint8 RGB, got {rgb.dtype} {rgb.shape}")
    ext = Path(path).suffix.lower() or ".png"
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(rgb[:, :, ::-1]))
    if not ok:
        raise FormatError(f"{path}: OpenCV cannot encode '{ext}'")
    atomic_write_bytes(path, buf, overwrite=overwrite)


def encode_depth_png(depth: np.ndarray) -> tuple[bytes, int]:
    """Encode metres as a KITTI depth PNG.

    Parameters
    ----------
    depth : (H, W) float, metres
        0, negative or non-finite = no measurement.

    Returns
    -------
    png : bytes
    clipped : int
        Valid pixels whose value fell outside [1, 65535] (depth >= 256 m or < 1/512 m)
        and were clipped into it.
    """
    import cv2

    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ParameterError(f"depth must be (H, W), got shape {depth.shape}")
    # Sparse maps are mostly empty: one pass finds the candidates (NaN fails ``> 0``), then
    # only those are checked for Inf and converted.
    flat = np.ravel(depth)
    index = np.flatnonzero(flat > 0)
    values = flat[index]
    finite = np.isfinite(values)
    if not finite.all():
        index, values = index[finite], values[finite]
    scaled = np.rint(values.astype(np.float64) * DEPTH_SCALE)
    clipped = int(np.count_nonzero((scaled < 1) | (scaled > 65535)))
    out = np.zeros(depth.shape, dtype=np.uint16)
    out.reshape(-1)[index] = np.clip(scaled, 1, 65535).astype(np.uint16)
    ok, buf = cv2.imencode(".png", out)
    if not ok:  # pragma: no cover - OpenCV always encodes uint16 PNG
        raise FormatError("OpenCV failed to encode a depth PNG")
    return buf.tobytes(), clipped


def write_depth_png(path: str | os.PathLike, depth: np.ndarray, *, overwrite: bool = True) -> int:
    """Write a KITTI-convention depth PNG (uint16, depth * 256, 0 = invalid), atomically.

    Returns the number of clipped pixels (depth >= 256 m cannot be stored); a warning is
    logged when it is not zero.
    """
    data, clipped = encode_depth_png(depth)
    if clipped:
        log.warning("%s: %d pixel(s) clipped to the uint16 range (depth >= 256 m)", path, clipped)
    atomic_write_bytes(path, data, overwrite=overwrite)
    return clipped


def decode_depth_png(data: bytes, *, source: str = "depth PNG") -> np.ndarray:
    """Decode KITTI depth PNG bytes to (H, W) float32 metres (0 = no measurement)."""
    import cv2

    img = _decode(data, Path(source), "depth PNG", cv2.IMREAD_UNCHANGED)
    if img.ndim != 2:
        raise FormatError(
            f"{source}: {img.shape[2]}-channel image, a depth PNG is single-channel uint16"
        )
    if img.dtype != np.uint16:
        raise FormatError(
            f"{source}: {img.dtype} PNG, a KITTI depth PNG is uint16 (value = depth * 256); "
            "8-bit files cannot hold metric depth"
        )
    peak = int(img.max()) if img.size else 0
    if 0 < peak <= 255:
        log.warning(
            "%s: every depth is below 1 m (max value %d): is this really depth * 256?", source, peak
        )
    return img.astype(np.float32) / np.float32(DEPTH_SCALE)


def read_depth_png(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI-convention depth PNG.

    Returns
    -------
    (H, W) float32
        Depth in metres, 0 where there is no measurement.

    Raises
    ------
    FormatError
        Missing, corrupt, 8-bit or multi-channel files.
    """
    path = Path(path)
    return decode_depth_png(_read_bytes(path, "depth PNG"), source=str(path))
