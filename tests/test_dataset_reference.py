"""``--store reference``: camera images referenced in place (a named root, a relative path, an
identity), read back, moved, verified, packed; on a KITTI raw tree of the real sequence."""

from __future__ import annotations

import json
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from _kitti_raw_tree import make_raw_tree
from sparsetools.cli.main import cli
from sparsetools.errors import FormatError
from sparsetools.io.dataset import MANIFEST_NAME, ManifestRow, read_manifest
from sparsetools.io.dataset_reader import DatasetReader
from sparsetools.pipeline.dataset import dataset_info, verify_dataset

pytestmark = pytest.mark.real

DATE = "2011_09_26"
DRIVE = f"{DATE}_drive_0001_sync"
N = 4  # frames


def run(*args, quiet=True):
    return CliRunner().invoke(cli, [*(["-q"] if quiet else []), *map(str, args)])


def make_raw(real_dir: Path, root: Path) -> Path:
    """root/2011_09_26/{calib, drive_0001_sync/{image_02, velodyne_points}/data} (N frames)."""
    return make_raw_tree(real_dir, root, {DRIVE: range(N)})


def image(raw: Path, i: int) -> Path:
    return raw / DATE / DRIVE / "image_02" / "data" / f"{i:010d}.png"


def kitti_raw(raw: Path, out: Path, store: str) -> None:
    r = run("dataset", "kitti-raw", raw, "-o", out, "--beams", 4, "--store", store)
    assert r.exit_code == 0, r.output


@pytest.fixture(scope="module")
def copy_ds(real_dir, tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("copy")
    out = base / "ds"
    kitti_raw(make_raw(real_dir, base / "raw"), out, "copy")
    return out


@pytest.fixture
def ref(real_dir, tmp_path) -> tuple[Path, Path]:
    """(raw root, reference dataset built from it), fresh per test: tests move and touch it."""
    raw = make_raw(real_dir, tmp_path / "raw")
    out = tmp_path / "ds_ref"
    kitti_raw(raw, out, "reference")
    return raw, out


def same_samples(a: DatasetReader, b: DatasetReader) -> None:
    assert a.ids == b.ids and len(a) == N
    for i in range(len(a)):
        sa, sb = a[i], b[i]
        assert sa.keys() == sb.keys()
        for k, va in sa.items():
            if isinstance(va, np.ndarray):
                assert va.dtype == sb[k].dtype and np.array_equal(va, sb[k]), k
            else:
                assert va == sb[k], k


def test_a_reference_dataset_reads_back_the_copy_arrays(copy_ds, ref):
    raw, out = ref
    table, info = read_manifest(out / MANIFEST_NAME)
    assert info["schema_version"] == 3 and info["roots"] == {"kitti": str(raw)}
    assert read_manifest(copy_ds / MANIFEST_NAME)[1]["schema_version"] == 2
    # the copy dataset's manifest has no reference columns at all (a version-2 manifest)
    assert "rgb_root" not in pq.read_table(copy_ds / MANIFEST_NAME).column_names
    assert not (out / "rgb").exists()  # no image copied
    for i, r in enumerate(ManifestRow.from_table(table)):
        src = image(raw, i)
        st = os.stat(src)
        assert r.rgb_root == "kitti"
        assert r.rgb_path == src.relative_to(raw).as_posix()
        assert (r.rgb_size, r.rgb_mtime_ns) == (st.st_size, st.st_mtime_ns)
    same_samples(DatasetReader(copy_ds), DatasetReader(out))
    # a reader goes to DataLoader workers by pickle: the roots go with it
    reader = pickle.loads(pickle.dumps(DatasetReader(out).split("train")))
    assert reader.roots == {"kitti": raw} and reader[0]["rgb"].shape == (375, 1242, 3)


def test_a_moved_root_is_given_again(copy_ds, ref, tmp_path):
    raw, out = ref
    moved = tmp_path / "elsewhere" / "kitti_raw"
    moved.parent.mkdir()
    raw.rename(moved)
    reader = DatasetReader(out)  # the manifest alone is read
    with pytest.raises(FormatError) as err:
        reader[0]
    msg = str(err.value)
    assert "\n" not in msg and f"'{reader.ids[0]}'" in msg and "--root kitti=PATH" in msg
    assert "roots={'kitti': PATH}" in msg
    same_samples(DatasetReader(copy_ds), DatasetReader(out, roots={"kitti": moved}))
    # verify: every image missing without the root, none with it
    r = run("dataset", "verify", out)
    assert r.exit_code == 1 and r.output.count("problem:") == N and "Traceback" not in r.output
    r = run("dataset", "verify", out, "--root", f"kitti={moved}", "--json")
    assert r.exit_code == 0, r.output
    report = json.loads(r.stdout)
    assert report["references"] == N and report["references_missing"] == 0
    assert run("dataset", "verify", out, "--root", "kitti").exit_code == 2  # NAME=PATH


def test_verify_reports_a_touched_image(ref):
    raw, out = ref
    first, second, third, fourth = (image(raw, i) for i in range(N))
    ids = DatasetReader(out).ids
    assert verify_dataset(out).ok
    # other bytes (another frame's image): size and hash differ
    before = os.stat(first)
    shutil.copyfile(second, first)
    # the same bytes, only the modification time changed
    st = os.stat(second)
    os.utime(second, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    # one byte flipped, size and modification time kept: the hash alone tells
    st3 = os.stat(third)
    data = bytearray(third.read_bytes())
    data[-20] ^= 0xFF
    third.write_bytes(bytes(data))
    os.utime(third, ns=(st3.st_atime_ns, st3.st_mtime_ns))
    fourth.unlink()
    report = verify_dataset(out)
    assert not report.ok
    assert (report.references, report.references_changed, report.references_missing) == (N, 2, 1)
    problems = "\n".join(report.problems)
    assert f"{ids[0]}: referenced image {first.relative_to(raw).as_posix()} (root 'kitti') " \
        f"changed since the build (size {before.st_size} -> {os.stat(first).st_size} differ)" \
        in problems  # fmt: skip
    assert f"{ids[2]}: referenced image" in problems and "sha256 differs" in problems
    assert f"'{ids[3]}'" in problems and "is missing from root 'kitti'" in problems
    assert not any(ids[1] in p for p in report.problems)  # same bytes: a warning only
    assert any(ids[1] in w and "touched" in w for w in report.warnings)
    # without hashes: the provenance record's rule (size, mtime; hash only for small files)
    quick = verify_dataset(out, check_hashes=False)
    flagged = {p.split(":")[0] for p in quick.problems if "changed since the build" in p}
    assert flagged == {ids[0], ids[1]}  # the flipped byte with its mtime kept goes unseen
    assert quick.references_changed == 2 and quick.references_missing == 1


def test_pack_equals_store_copy(copy_ds, ref, tmp_path):
    raw, out = ref
    packed = tmp_path / "packed"
    r = run("dataset", "pack", out, "-o", packed, "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    sizes = sum(os.stat(image(raw, i)).st_size for i in range(N))
    assert s["samples"] == s["referenced_images"] == N and s["referenced_bytes"] == sizes
    # the same files, byte for byte, as --store copy (the run record and the route's staged
    # sources are not part of the dataset: .sparsetools/ differs, .sources/ is not packed)

    def files(root):
        return {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*")
                if p.is_file() and not {".sparsetools", ".sources"} & set(p.relative_to(root).parts)}  # fmt: skip

    a, b = files(copy_ds), files(packed)
    assert sorted(a) == sorted(b) and all(a[k] == b[k] for k in a)
    # ... hence the same rows (no field differs) and build information, a version-2 manifest
    ta, ia = read_manifest(copy_ds / MANIFEST_NAME)
    tb, ib = read_manifest(packed / MANIFEST_NAME)
    assert ManifestRow.from_table(ta) == ManifestRow.from_table(tb) and ia == ib
    same_samples(DatasetReader(copy_ds), DatasetReader(packed))
    assert verify_dataset(packed).ok
    # rerun: nothing to do; a folder pack did not write is refused
    again = json.loads(run("dataset", "pack", out, "-o", packed, "--json").stdout)
    assert again["processed"] == 0 and again["skipped_existing"] == N
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    r = run("dataset", "pack", out, "-o", foreign)
    assert r.exit_code != 0 and "was not written by dataset pack" in r.output
    assert "Traceback" not in r.output
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]


def test_pack_refuses_a_changed_image(ref, tmp_path):
    raw, out = ref
    shutil.copyfile(image(raw, 1), image(raw, 0))
    packed = tmp_path / "packed"
    r = run("dataset", "pack", out, "-o", packed)
    assert r.exit_code != 0 and "changed since the build" in r.output
    assert not (packed / MANIFEST_NAME).exists()


@pytest.mark.parametrize("bad", ["../outside.png", "/etc/hostname", "link.png"])
def test_a_reference_leaving_its_root_is_refused(ref, tmp_path, bad):
    raw, out = ref
    outside = tmp_path / "outside.png"
    shutil.copy(image(raw, 0), outside)
    (raw / "link.png").symlink_to(outside)  # inside the root, pointing out of it
    path = out / MANIFEST_NAME
    table = pq.read_table(path)
    rgb = table.column("rgb_path").to_pylist()
    rgb[0] = bad
    i = table.column_names.index("rgb_path")
    table = table.set_column(i, "rgb_path", __import__("pyarrow").array(rgb))
    pq.write_table(table, path)  # the metadata (schema version, roots) kept
    if bad == "link.png":
        reader = DatasetReader(out)
        with pytest.raises(FormatError, match="outside its root 'kitti'") as err:
            reader[0]
        assert "\n" not in str(err.value)
        reader[1]  # the other samples read
        r = run("dataset", "verify", out)
        assert r.exit_code == 1 and "resolves outside its root 'kitti'" in r.output
        r = run("dataset", "pack", out, "-o", tmp_path / "packed")
        assert r.exit_code != 0 and "outside its root" in r.output
        assert not (tmp_path / "packed").exists()
    else:
        with pytest.raises(FormatError, match="absolute paths and '..' are refused"):
            DatasetReader(out)
        r = run("dataset", "verify", out)
        assert r.exit_code != 0 and len(r.output.strip().splitlines()) == 1
    assert "Traceback" not in r.output


def test_link_is_the_old_spelling_of_store_link(real_dir, copy_ds, tmp_path):
    raw = make_raw(real_dir, tmp_path / "raw")
    sparse = copy_ds / ".sources" / "gt"
    old, new = tmp_path / "old", tmp_path / "new"
    r = run("dataset", "build", "-o", old, "--rgb", raw, "--sparse", sparse, "--link", quiet=False)
    assert r.exit_code == 0, r.output
    warned = [ln for ln in r.stderr.splitlines() if "deprecated:" in ln]
    assert len(warned) == 1
    assert warned[0].endswith(
        "deprecated: --link is now --store link (the old spelling goes in 0.4)"
    )
    r = run("dataset", "build", "-o", new, "--rgb", raw, "--sparse", sparse, "--store", "link")
    assert r.exit_code == 0, r.output
    assert read_manifest(old / MANIFEST_NAME)[0].equals(read_manifest(new / MANIFEST_NAME)[0])
    run_json = json.loads((old / ".sparsetools" / "run.json").read_text())
    assert run_json["settings"]["link"] is True and "store" not in run_json["settings"]
    both = run("dataset", "build", "-o", tmp_path / "x", "--rgb", raw, "--sparse", sparse,
               "--link", "--store", "copy")  # fmt: skip
    assert both.exit_code == 2 and "give --store link only" in both.output
    # dataset build --store reference: the --rgb folder is the root 'rgb'; a rerun with
    # another store is refused, naming the option
    ref = tmp_path / "ref"
    assert run("dataset", "build", "-o", ref, "--rgb", raw, "--sparse", sparse, "--store",
               "reference").exit_code == 0  # fmt: skip
    assert read_manifest(ref / MANIFEST_NAME)[1]["roots"] == {"rgb": str(raw)}
    r = run("dataset", "build", "-o", ref, "--rgb", raw, "--sparse", sparse)
    assert r.exit_code != 0 and "--store" in r.output


def _disk_files(root: Path) -> dict[str, int]:
    """Sizes of the regular files under root, links not followed (an independent walk)."""
    out = {}
    for folder, _, names in os.walk(root):
        for n in names:
            p = Path(folder, n)
            if p.is_file() and not p.is_symlink():
                out[p.relative_to(root).as_posix()] = p.stat().st_size
    return out


def test_info_counts_the_dataset_and_the_referenced_bytes(copy_ds, ref, tmp_path):
    raw, out = ref
    images = sum(os.stat(image(raw, i)).st_size for i in range(N))
    on_disk = _disk_files(out)
    d = dataset_info(out)
    assert (d.referenced_files, d.referenced_bytes, d.missing_references) == (N, images, 0)
    assert "rgb" not in d.bytes and d.total_bytes == sum(on_disk.values())
    assert d.bytes["sources"] == sum(v for k, v in on_disk.items() if k.startswith(".sources/"))
    text = str(d)
    assert "size in the dataset" in text and f"({N} image(s) kept in place)" in text
    c = dataset_info(copy_ds)
    assert c.bytes["rgb"] == images and c.referenced_files == 0 and "size referenced" not in str(c)
    assert c.total_bytes == sum(_disk_files(copy_ds).values())
    # the tree moved: counted as not found, then found again with --root
    moved = tmp_path / "moved"
    raw.rename(moved)
    assert dataset_info(out).missing_references == N
    r = run("dataset", "info", out, "--root", f"kitti={moved}", "--json")
    assert r.exit_code == 0 and json.loads(r.stdout)["referenced_bytes"] == images


def test_report_thumbnails_and_viz_read_referenced_images(copy_ds, ref):
    """The dataset report's thumbnails and viz's dataset frames find a referenced image where
    it is (not in the dataset), the thumbnail the same as the copy dataset's."""
    from sparsetools.pipeline.dataset.report_data import thumbnail
    from sparsetools.pipeline.viz import _dataset_frames

    raw, out = ref
    a, b = DatasetReader(copy_ds), DatasetReader(out)
    ta = thumbnail(a, a.row(0), max_depth=80.0)
    tb = thumbnail(b, b.row(0), max_depth=80.0)
    assert ta == tb and len(ta.jpeg) > 0
    frames, _, _ = _dataset_frames(out, None, None)
    assert image(raw, 0) in frames[0].sources
