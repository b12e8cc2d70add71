"""The resume rule for a command that writes one file (:class:`OutputFile`: ``viz``,
``eval -o``, reports, plots) or one tree of files (:class:`OutputTree`), where
:class:`~.provenance.OutputFolder` is the rule for a folder of frames.

Both keep the rule of :mod:`.provenance`: up to date when the same command, settings and
version made the output from unchanged inputs; an existing output without such a record is
refused unless ``overwrite``.
"""

from __future__ import annotations

from pathlib import Path

from .._version import __version__
from ..errors import OutputError
from ..io.provenance import (
    FileIdentity,
    FrameRecord,
    RunRecord,
    file_identity,
    read_file_record,
    read_frame_records,
    read_run_record,
    write_file_record,
    write_frame_records,
    write_run_record,
)
from .provenance import check_made_by, option_names, settings_dict

__all__ = ["OutputFile", "OutputTree"]


class OutputFile:
    """The resume rule for a command that writes ONE file (``viz``, ``eval -o``).

    The file is up to date when its record (``<dir>/.sparsetools/files/<name>.json``) names
    the same command, settings and version and its inputs are unchanged; an existing file
    without such a record, or made otherwise, is refused unless ``overwrite``.

    Parameters
    ----------
    path : path-like
    command : str
    settings : dataclass or mapping
    sources : iterable of path-like
        Input files.
    overwrite : bool
    """

    def __init__(
        self, path, command: str, settings, sources, *, overwrite: bool = False,
        noun: str = "a file",
    ):  # fmt: skip
        self.path = Path(path)
        self.noun = noun
        self.command = command
        self.settings = settings_dict(settings)
        self.names = option_names(settings)
        self.sources = tuple(Path(p) for p in sources)
        self.overwrite = overwrite

    def _identities(self) -> tuple[FileIdentity, ...]:
        return tuple(file_identity(p) for p in self.sources)

    def up_to_date(self) -> bool:
        """True when the file need not be written again; raises when it may not be."""
        if self.path.exists() and not self.path.is_file():
            raise OutputError(f"{self.path} exists and is not a file")
        if self.overwrite or not self.path.exists():
            return False
        rec = read_file_record(self.path)
        if rec is None:
            raise OutputError(
                f"{self.path} exists and was not written by this command: use --overwrite or "
                "another -o"
            )
        run, frame = rec
        check_made_by(run, command=self.command, settings=self.settings, names=self.names,
                      noun=self.noun, place=self.path)  # fmt: skip
        now = self._identities()
        same = (
            len(now) == len(frame.inputs)
            and all(a.same_file(b) for a, b in zip(frame.inputs, now, strict=True))
            and frame.key == self.path.name
        )
        return same

    def record(self) -> None:
        """Record the file just written."""
        write_file_record(
            self.path,
            RunRecord(self.command, __version__, self.settings),
            FrameRecord(self.path.name, {"file": self.path.name}, self._identities()),
        )


class OutputTree:
    """The resume rule for a command that makes a whole folder at once (``synth-scene``).

    The folder is up to date when its record names the same command, settings and version and
    every file the record lists exists; a folder made otherwise, or a non-empty folder without
    a record, is refused unless ``overwrite``.
    """

    KEY = "tree"

    def __init__(self, out, command: str, settings, *, noun: str, overwrite: bool = False):
        self.out = Path(out)
        self.command = command
        self.settings = settings_dict(settings)
        self.names = option_names(settings)
        self.noun = noun
        self.overwrite = overwrite

    def up_to_date(self) -> bool:
        if self.out.exists() and not self.out.is_dir():
            raise OutputError(f"{self.out} exists and is not a folder")
        if self.overwrite or not self.out.is_dir() or not any(self.out.iterdir()):
            return False
        run = read_run_record(self.out)
        if run is None:
            raise OutputError(
                f"{self.out} is not empty and has no record of what made it: use --overwrite "
                "or another folder"
            )
        check_made_by(run, command=self.command, settings=self.settings, names=self.names,
                      noun=self.noun, place=self.out)  # fmt: skip
        rec = read_frame_records(self.out).get(self.KEY)
        return rec is not None and all((self.out / rel).is_file() for rel in rec.outputs.values())

    def record(self, files) -> None:
        """Record the files the command wrote (paths inside the folder)."""
        outputs = {}
        for i, f in enumerate(sorted(Path(f) for f in files)):
            try:
                outputs[f"file{i}"] = f.resolve().relative_to(self.out.resolve()).as_posix()
            except ValueError:
                continue
        write_run_record(self.out, RunRecord(self.command, __version__, self.settings))
        write_frame_records(self.out, {self.KEY: FrameRecord(self.KEY, outputs)})
