"""``sparsetools viz``: sparse depth over an image: one picture (several maps as panels), or
over many frames contact sheets (:class:`SheetJob`) and videos (:class:`VideoJob`)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import OutputError, ParameterError
from .core import BatchJob, FrameStats, FrameTask
from .output_file import OutputFile

__all__ = [
    "ManyVizSettings",
    "SheetJob",
    "VideoJob",
    "VizFrame",
    "VizSettings",
    "default_labels",
    "render_viz",
    "select_frames",
    "viz_frames",
]

PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class VizSettings:
    """How the picture is drawn.

    Attributes
    ----------
    max_depth : float, metres
        Top of the colour scale, shown in red (0 m is blue, turbo colour map; ``--color-max``).
    dilate : int, pixels
        Each point is drawn as a (2 * dilate + 1)^2 square.
    horizontal : bool
        Panels left to right (default: stacked).
    labels : tuple of str, optional
        Panel labels (None: none).
    colorbar : bool
    """

    max_depth: float = field(default=80.0, metadata={"option": "--color-max"})
    dilate: int = 2
    horizontal: bool = False
    labels: tuple[str, ...] | None = None
    colorbar: bool = True


def default_labels(paths: list[Path]) -> list[str]:
    """File stems, or parent/stem when stems repeat (raw/0001.png vs jbf/0001.png)."""
    stems = [p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [f"{p.parent.name}/{p.stem}" for p in paths]


def render_viz(
    depth: list[str | os.PathLike],
    out: str | os.PathLike,
    settings: VizSettings,
    *,
    image: str | os.PathLike | None = None,
    overwrite: bool = False,
) -> tuple[str, tuple[int, int] | None]:
    """Draw ``depth`` maps over ``image`` and write the picture (atomically).

    Returns
    -------
    status : {"written", "up to date"}
        An up-to-date picture (same inputs, same settings) is not drawn again.
    size : (width, height) or None
    """
    from ..io.depth_files import read_depth_file
    from ..io.image import read_image, write_image
    from ..ops.viz import depth_panels

    out = Path(out)
    depth = [Path(p) for p in depth]
    if settings.labels is not None and len(settings.labels) != len(depth):
        raise ParameterError(
            f"{len(settings.labels)} label(s) for {len(depth)} depth map(s)", param="labels"
        )
    if out.suffix.lower() not in PICTURE_SUFFIXES:
        raise ParameterError("the picture is written as .png or .jpg", param="--out")
    sources = [*depth, *([Path(image)] if image is not None else [])]
    if out.resolve() in {p.resolve() for p in sources}:
        raise OutputError(f"output {out} would replace an input file: choose another -o")
    target = OutputFile(out, "viz", settings, sources, overwrite=overwrite, noun="a picture")
    if target.up_to_date():
        return "up to date", None
    maps = [read_depth_file(p) for p in depth]
    rgb = read_image(image) if image is not None else None
    picture = depth_panels(
        rgb,
        maps,
        labels=list(settings.labels) if settings.labels else None,
        max_depth=settings.max_depth,
        dilate=settings.dilate,
        vertical=not settings.horizontal,
        with_colorbar=settings.colorbar,
    )
    write_image(out, picture)
    target.record()
    return "written", (picture.shape[1], picture.shape[0])


# -- many frames: contact sheets and videos --------------------------------------------------------

#: ``viz`` over many frames writes contact sheets (PNG pages) or one MP4 video per sequence.
MODES = ("sheet", "video")
#: The frame key used for the video of a flat folder (frames without a sequence).
FLAT_VIDEO = "video"
#: Labels of the panels of a dataset's samples (sparse input, and ground truth when every
#: sample has one).
DATASET_LABELS = ("sparse", "GT")
#: OpenCV's FourCC of the MP4 videos (MPEG-4 part 2: in every opencv-python wheel).
FOURCC = "mp4v"


@dataclass(frozen=True)
class ManyVizSettings:
    """What contact sheets and videos depend on (recorded in ``-o``; another value of any
    field is refused unless ``--overwrite``).

    Attributes
    ----------
    mode : {"sheet", "video"}
    max_depth : float, metres
        Top of the colour scale (``--color-max``).
    dilate : int, pixels
        Each point drawn as a (2 * dilate + 1)^2 square (at full resolution).
    horizontal : bool
        Several depth inputs of a frame left to right (default: stacked).
    labels : tuple of str, optional
        One label per depth input, written on each panel (None: none).
    colorbar : bool
        A colour bar below each sheet page / video frame.
    grid : str, optional
        ``COLSxROWS`` tiles of a sheet page (sheets only; default ``4x3``; a ``(cols, rows)``
        pair is accepted and written so).
    tile_width : int, pixels, optional
        Width of one sheet cell (sheets only; default 320).
    fps : float, optional
        Frames per second of a video (videos only; default 10, KITTI's LiDAR rate).
    frame_range : str
        ``FROM:TO[:STEP]`` over the sorted frame keys ("" = all frames).
    split : str, optional
        The split of a dataset input.
    """

    mode: str = field(default="sheet", metadata={"option": "--sheet/--video"})
    max_depth: float = field(default=80.0, metadata={"option": "--color-max"})
    dilate: int = 2
    horizontal: bool = False
    labels: tuple[str, ...] | None = None
    colorbar: bool = True
    grid: str | tuple[int, int] | None = None
    tile_width: int | None = None
    fps: float | None = None
    frame_range: str = ""
    split: str | None = None

    def __post_init__(self) -> None:
        from ..errors import UsageError
        from ..validate import (
            check_choice,
            check_int_range,
            check_positive,
            parse_frame_range,
            parse_size,
        )

        check_choice(self.mode, "mode", MODES)
        check_positive(self.max_depth, "--color-max")
        check_int_range(self.dilate, "dilate", low=0, high=50)
        parse_frame_range(self.frame_range, "--frame-range")
        if self.labels is not None:
            object.__setattr__(self, "labels", tuple(str(s) for s in self.labels))
        if self.mode == "sheet":
            if self.fps is not None:
                raise UsageError("--fps is an option of --video, not of --sheet")
            cols, rows = parse_size(self.grid if self.grid is not None else (4, 3), "--grid")
            object.__setattr__(self, "grid", f"{cols}x{rows}")
            width = 320 if self.tile_width is None else self.tile_width
            object.__setattr__(self, "tile_width", check_int_range(width, "--tile-width", low=32))
        else:
            for name, value in (("--grid", self.grid), ("--tile-width", self.tile_width)):
                if value is not None:
                    raise UsageError(f"{name} is an option of --sheet, not of --video")
            fps = 10.0 if self.fps is None else float(self.fps)
            object.__setattr__(self, "fps", check_positive(fps, "--fps"))

    @property
    def columns_rows(self) -> tuple[int, int]:
        """``grid`` as ``(cols, rows)`` (sheets only)."""
        from ..validate import parse_size

        return parse_size(self.grid, "--grid")


@dataclass(frozen=True)
class VizFrame:
    """One frame of a sheet or video: its key and files (or its sample in a dataset).

    Attributes
    ----------
    key : FrameKey
    depths : tuple of Path
        One depth map per input (empty for a dataset sample).
    image : Path, optional
        Camera image under the points (None: black).
    sample : str, optional
        The sample id in the dataset (dataset inputs).
    sources : tuple of Path
        Every input file of the frame (resume identity).
    """

    key: object
    depths: tuple[Path, ...] = ()
    image: Path | None = None
    sample: str | None = None
    sources: tuple[Path, ...] = ()

    @property
    def label(self) -> str:
        return str(self.key)


def select_frames(frames: list, frame_range: str) -> list:
    """``frames`` (sorted) sliced by ``--frame-range FROM:TO[:STEP]``.

    Raises
    ------
    FormatError
        The range selects no frame.
    """
    from ..errors import FormatError
    from ..validate import parse_frame_range

    start, stop, step = parse_frame_range(frame_range, "--frame-range")
    out = frames[start:stop:step]
    if not out:
        raise FormatError(f"--frame-range {frame_range} selects none of the {len(frames)} frame(s)")
    return out


def viz_frames(
    depth: list[str | os.PathLike],
    *,
    image: str | os.PathLike | None = None,
    split: str | None = None,
    frame_range: str = "",
) -> tuple[list[VizFrame], Path | None, tuple[str, ...] | None]:
    """The frames ``viz`` draws over many frames, matched by ``(sequence, frame)``.

    Parameters
    ----------
    depth : list of path-like
        Depth inputs (files, folders, folder trees, sparsetools output folders, KITTI
        depth-completion trees; see :mod:`sparsetools.io.sources`), one per panel, matched by
        frame key with the first; or ONE dataset folder (``dataset build``).
    image : path-like, optional
        Images matched by frame (a folder), or one file for a single frame.
    split : str, optional
        The split of a dataset input.
    frame_range : str
        ``FROM:TO[:STEP]`` over the sorted keys of the first input (before matching).

    Returns
    -------
    frames : list of VizFrame
        Sorted by key.
    dataset : Path or None
        The dataset folder, for a dataset input.
    panels : tuple of str or None
        The panels of a dataset sample (``sparse`` and ``GT``); None for depth inputs.

    Raises
    ------
    FormatError
        An input without depth maps, a frame of the first input that another input or the
        image folder lacks, a range selecting nothing.
    UsageError
        ``--split`` without a dataset, ``--image`` with one, a dataset with other inputs.
    """
    from ..errors import UsageError
    from ..io.dataset import MANIFEST_NAME
    from ..io.sources import attach, depth_frames

    paths = [Path(p) for p in depth]
    datasets = [p for p in paths if (p / MANIFEST_NAME).is_file()]
    if datasets:
        if len(paths) > 1:
            raise UsageError(f"{datasets[0]} is a dataset: give it alone (one dataset per run)")
        if image is not None:
            raise UsageError("--image: a dataset holds its own images")
        return _dataset_frames(paths[0], split, frame_range)
    if split is not None:
        raise UsageError("--split picks a split of a dataset folder; no DEPTH is one")
    base = select_frames(depth_frames([paths[0]], role="depth", option="DEPTH"), frame_range)
    layers = [[f.depth for f in base]]
    for p in paths[1:]:
        matched, _ = attach(base, p, "depth", role="depth", option="DEPTH", shared_ok=False,
                            required=True)  # fmt: skip
        layers.append([f.depth for f in matched])
    with_image, _ = attach(base, image, "image", role="image", option="--image", shared_ok=False,
                           required=True)  # fmt: skip
    frames = []
    for i, f in enumerate(with_image):
        depths = tuple(layer[i] for layer in layers)
        files = (*depths, *((f.image,) if f.image is not None else ()))
        frames.append(VizFrame(key=f.key, depths=depths, image=f.image, sources=files))
    return frames, None, None


def _dataset_frames(root: Path, split: str | None, frame_range: str):
    from ..io.dataset import MANIFEST_NAME
    from ..io.dataset_reader import DatasetReader
    from ..io.sources import FrameKey

    reader = DatasetReader(root, split=split)
    frames = []
    for i in range(len(reader)):
        r = reader.row(i)
        files = [root / MANIFEST_NAME, reader.rgb_path(i)]  # in the dataset, or referenced
        for rel, what in ((r.sparse_parquet, "sparse_parquet"), (r.sparse_path, "sparse_path"),
                          (r.gt_path, "gt_path")):  # fmt: skip
            if rel is not None:
                files.append(reader.path(rel, what=what))
        try:
            key = FrameKey(r.sequence or "", r.frame)
        except ParameterError:  # a name that is no path-like key: the sample id labels it
            key = r.id
        frames.append(VizFrame(key=key, sample=r.id, sources=tuple(dict.fromkeys(files))))
    if not frames:
        from ..errors import FormatError

        raise FormatError(f"{root}: the dataset{f' split {split}' if split else ''} is empty")
    frames.sort(key=lambda f: (f.key.sequence, f.key.frame) if isinstance(f.key, FrameKey)
                else ("", str(f.key)))  # fmt: skip
    frames = select_frames(frames, frame_range)
    has_gt = all(reader.row(f.sample).gt_path is not None for f in frames)
    return frames, root, DATASET_LABELS if has_gt else DATASET_LABELS[:1]


@dataclass(frozen=True)
class ManyVizInput:
    """The frames of one sheet page or one video."""

    frames: tuple[VizFrame, ...]


def _load(job, frame: VizFrame, reader):
    """(image or None, list of depth maps) of one frame."""
    from ..io.depth_files import read_depth_file
    from ..io.image import read_image

    if frame.sample is not None:
        s = reader.sample(frame.sample)
        maps = [s["sparse"]]
        if len(job.panels) > 1:
            maps.append(s["gt"])
        return s["rgb"], maps
    maps = [read_depth_file(p) for p in frame.depths]
    return (read_image(frame.image) if frame.image is not None else None), maps


#: The dataset reader of this process by (folder, split, manifest size and time): a worker
#: reads the manifest once, not once per page or video.
_READERS: dict = {}


def _reader(job):
    if job.dataset is None:
        return None
    from ..io.dataset import MANIFEST_NAME
    from ..io.dataset_reader import DatasetReader

    st = os.stat(Path(job.dataset) / MANIFEST_NAME)  # a rebuilt dataset is read again
    key = (job.dataset, job.settings.split, st.st_size, st.st_mtime_ns)
    if key not in _READERS:
        _READERS.clear()
        _READERS[key] = DatasetReader(job.dataset, split=job.settings.split)
    return _READERS[key]


def _panels(job, rgb, maps, *, panel_width=None, caption=None, colorbar=False):
    from ..ops.viz import depth_panels

    s = job.settings
    labels = list(job.labels) if job.labels else None
    return depth_panels(
        rgb, maps, labels=labels, max_depth=s.max_depth, dilate=s.dilate,
        vertical=not s.horizontal, with_colorbar=colorbar, panel_width=panel_width,
        caption=caption,
    )  # fmt: skip


def _check_labels(job) -> None:
    if job.labels is not None and len(job.labels) != len(job.panels):
        raise ParameterError(
            f"{len(job.labels)} label(s) for {len(job.panels)} panel(s) per frame",
            param="--labels",
        )


@dataclass(frozen=True)
class SheetStats(FrameStats):
    """One contact-sheet page: tiles drawn, page size (pixels)."""

    frames: int
    width: int
    height: int


@dataclass(frozen=True)
class VideoStats(FrameStats):
    """One video: frames written, frame size (pixels)."""

    frames: int
    width: int
    height: int


@dataclass(frozen=True)
class _ManyVizJob(BatchJob[ManyVizInput]):
    """Shared part of the sheet and video jobs (picklable).

    Attributes
    ----------
    settings : ManyVizSettings
    panels : tuple of str
        What each frame shows, one entry per panel (depth inputs, or a dataset's panels).
    labels : tuple of str, optional
        Panel labels written on the panels (None: none).
    dataset : str, optional
        The dataset folder of a dataset input.
    """

    command = "viz"
    settings: ManyVizSettings = field(default_factory=ManyVizSettings)
    panels: tuple[str, ...] = ("depth",)
    labels: tuple[str, ...] | None = None
    dataset: str | None = None

    def __post_init__(self) -> None:
        _check_labels(self)

    def record(self) -> dict:
        from .provenance import settings_dict

        return {**settings_dict(self.settings), "dataset": self.dataset}

    def option_names(self) -> dict:
        from .provenance import option_names

        return {**option_names(self.settings), "dataset": "DEPTH"}


@dataclass(frozen=True)
class SheetJob(_ManyVizJob):
    """``viz --sheet``: pages of ``cols x rows`` tiles (depth over image, the frame key
    written once per tile), ``OUT/sheet_0001.png``, ... in frame-key order; one task per
    page.

    Attributes
    ----------
    tile_size : (width, height), optional
        Size of one cell, fixed by :meth:`planned` from the first frame's size.
    """

    noun = "contact sheets"
    stats_type = SheetStats
    tile_size: tuple[int, int] | None = None

    def planned(self, frames: list) -> SheetJob:
        from dataclasses import replace

        from ..ops.viz import depth_panels

        if not frames:
            return self
        h, w = _frame_shape(self, frames[0])
        zeros = np.zeros((h, w), np.float32)
        pw = self._panel_width()
        tile = depth_panels(None, [zeros] * len(self.panels), vertical=not self.settings.horizontal,
                            with_colorbar=False, panel_width=pw)  # fmt: skip
        cell_w = self.settings.tile_width
        cell_h = tile.shape[0] + 2 * SHEET_MARGIN
        return replace(self, tile_size=(cell_w, cell_h))

    def _panel_width(self) -> int:
        inner = self.settings.tile_width - 2 * SHEET_MARGIN
        n = len(self.panels)
        if self.settings.horizontal and n > 1:
            return max(8, (inner - PANEL_GAP * (n - 1)) // n)
        return inner

    def tasks(self, frames: list, out_dir: Path) -> list[FrameTask[ManyVizInput]]:
        cols, rows = self.settings.columns_rows
        per_page = cols * rows
        pages = [frames[i : i + per_page] for i in range(0, len(frames), per_page)]
        digits = max(4, len(str(len(pages))))
        tasks = []
        for n, page in enumerate(pages, start=1):
            name = f"sheet_{n:0{digits}d}"
            sources = tuple(dict.fromkeys(p for f in page for p in f.sources))
            tasks.append(FrameTask(name, ManyVizInput(tuple(page)),
                                   {"sheet": Path(out_dir) / f"{name}.png"}, sources))  # fmt: skip
        return tasks

    def __call__(self, task: FrameTask[ManyVizInput]) -> SheetStats:
        from ..io.image import write_image
        from ..ops.colormap import side_by_side
        from ..ops.viz import colorbar, contact_sheet

        reader = _reader(self)
        pw = self._panel_width()
        tiles = []
        for frame in task.inputs.frames:
            rgb, maps = _load(self, frame, reader)
            tiles.append(_panels(self, rgb, maps, panel_width=pw))
        page = contact_sheet(
            tiles, [f.label for f in task.inputs.frames], grid=self.settings.columns_rows,
            tile_size=self.tile_size, margin=SHEET_MARGIN,
        )  # fmt: skip
        if self.settings.colorbar:
            page = side_by_side([page, colorbar(page.shape[1], max_depth=self.settings.max_depth)])
        write_image(task.outputs["sheet"], page)
        return SheetStats(frames=len(tiles), width=page.shape[1], height=page.shape[0])

    def finish(self, summary, tasks, out_dir: Path) -> dict:
        return {"pages": len(tasks), "frames": sum(len(t.inputs.frames) for t in tasks),
                "grid": self.settings.grid, "output": str(out_dir)}  # fmt: skip


@dataclass(frozen=True)
class VideoJob(_ManyVizJob):
    """``viz --video``: one MP4 per sequence (``OUT/<sequence>.mp4``; ``OUT/video.mp4`` for a
    flat folder), each frame the depth inputs over the image with the frame key written once;
    one task per sequence."""

    noun = "videos"
    stats_type = VideoStats

    def tasks(self, frames: list, out_dir: Path) -> list[FrameTask[ManyVizInput]]:
        groups: dict[str, list[VizFrame]] = {}
        for f in frames:
            seq = getattr(f.key, "sequence", "") or FLAT_VIDEO
            groups.setdefault(seq, []).append(f)
        tasks = []
        for seq, group in groups.items():
            sources = tuple(dict.fromkeys(p for f in group for p in f.sources))
            target = Path(out_dir) / f"{seq}.mp4"
            tasks.append(FrameTask(seq, ManyVizInput(tuple(group)), {"video": target}, sources))
        return tasks

    def __call__(self, task: FrameTask[ManyVizInput]) -> VideoStats:
        import cv2

        from ..errors import OutputError
        from ..io.atomic import atomic_path
        from ..ops.viz import fit_picture

        reader = _reader(self)
        size = even = None
        n = 0
        with atomic_path(task.outputs["video"]) as tmp:
            writer = None
            try:
                for frame in task.inputs.frames:
                    rgb, maps = _load(self, frame, reader)
                    pic = _panels(self, rgb, maps, caption=frame.label,
                                  colorbar=self.settings.colorbar)  # fmt: skip
                    if size is None:  # the first frame fixes the size
                        size = (pic.shape[1], pic.shape[0])
                        even = (size[0] + size[0] % 2, size[1] + size[1] % 2)  # MPEG-4 wants it
                        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*FOURCC),
                                                 float(self.settings.fps), even)  # fmt: skip
                        if not writer.isOpened():
                            raise OutputError(
                                f"OpenCV cannot write an MP4 ({FOURCC}) video to {tmp.parent}"
                            )
                    if pic.shape[:2] != size[::-1]:  # another frame size: fitted, aspect kept
                        pic = fit_picture(pic, size)
                    pad = ((0, even[1] - size[1]), (0, even[0] - size[0]), (0, 0))
                    pic = np.pad(pic, pad, constant_values=255)
                    writer.write(np.ascontiguousarray(pic[:, :, ::-1]))
                    n += 1
            finally:
                if writer is not None:
                    writer.release()
        return VideoStats(frames=n, width=even[0], height=even[1])

    def finish(self, summary, tasks, out_dir: Path) -> dict:
        return {"videos": len(tasks), "frames": sum(len(t.inputs.frames) for t in tasks),
                "fps": self.settings.fps, "output": str(out_dir)}  # fmt: skip


#: Background around each tile inside its sheet cell, pixels.
SHEET_MARGIN = 2
#: White gap between the panels of one frame (``ops.colormap.side_by_side``), pixels.
PANEL_GAP = 4


def _frame_shape(job, frame: VizFrame) -> tuple[int, int]:
    """(H, W) of a frame's depth maps, from the manifest or the first depth map."""
    if frame.sample is not None:
        r = _reader(job).row(frame.sample)
        return int(r.height), int(r.width)
    from ..io.depth_files import read_depth_file

    return read_depth_file(frame.depths[0]).shape[:2]
