"""Speed changes of issue 18 in the batch layer change no output and no record.

- file identities through the per-run folder cache equal the plain resolve-and-stat ones;
- record paths are the ones the old ``relative_to`` made;
- thread limits are set where they should be (one BLAS thread while frames run, one thread
  of everything in pool workers) and restored;
- commands write the bytes the code before issue 18 wrote (digests below, made by that code:
  ``git archive`` of the commit before the change, run on the checkout's sample data);
- a one-frame ``project`` imports no heavy library.

The kernels' fast paths are tests/test_speed_equivalence.py.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.provenance import file_identity
from sparsetools.pipeline import executors
from sparsetools.pipeline.provenance import OutputFolder

ROOT = Path(__file__).resolve().parent.parent
SYNTH = ROOT / "sample_data" / "synthetic"
KITTI = ROOT / "sample_data" / "kitti"


# -- file identities and record paths ------------------------------------------------------------


def test_cached_file_identities_equal_the_plain_ones(tmp_path, monkeypatch):
    data = tmp_path / "data"
    (data / "seq").mkdir(parents=True)
    small = data / "seq" / "calib.txt"
    small.write_text("P2: 1 0 0\n")
    big = data / "seq" / "000000.bin"
    big.write_bytes(os.urandom(70_000))
    (tmp_path / "link_dir").symlink_to(data)
    (data / "link_file.bin").symlink_to(big)
    raw = tmp_path / "raw"
    raw.mkdir()
    (raw / "calib_cam_to_cam.txt").write_text("x")
    monkeypatch.chdir(tmp_path)
    paths = [
        small, big, tmp_path / "link_dir" / "seq" / "000000.bin", data / "link_file.bin",
        data / "seq" / ".." / "seq" / "calib.txt", Path("data/seq/calib.txt"),
        data / "missing.bin", raw, str(big),
    ]  # fmt: skip
    folders: dict[str, str] = {}
    for p in paths:
        for _ in range(2):  # the second time from the cache
            assert file_identity(p, folders=folders) == file_identity(p), p
    assert file_identity(small, folders=folders).sha256 is not None
    assert file_identity(big, folders=folders).sha256 is None


def old_rel(out: Path, path) -> str:
    try:
        return Path(os.path.abspath(path)).relative_to(os.path.abspath(out)).as_posix()
    except ValueError:
        return os.path.abspath(path)


def test_record_paths_are_the_old_ones(tmp_path, monkeypatch):
    out = tmp_path / "out"
    folder = OutputFolder(out, "test", {})
    cases = [out / "a.png", out / "seq" / "b.png", out / "calib" / "s" / "c.json",
             tmp_path / "outside.png", tmp_path / "out2" / "x.png", Path("out/rel.png"),
             str(out / "d.npy"), out]  # fmt: skip
    monkeypatch.chdir(tmp_path)
    for p in cases:
        assert folder._rel(p) == old_rel(out, p), p
    trailing = OutputFolder(str(out) + os.sep, "test", {})
    assert trailing._rel(out / "a.png") == "a.png"


# -- threads -------------------------------------------------------------------------------------


def blas_threads() -> list[int]:
    import numpy  # noqa: F401 - loads numpy's OpenBLAS

    return [get() for _, get in executors._loaded_openblas()]


def test_blas_limit_is_set_and_restored():
    before = blas_threads()
    if not before:
        pytest.skip("no OpenBLAS loaded in this process")
    with executors.limit_blas_threads(1):
        assert blas_threads() == [1] * len(before)
    assert blas_threads() == before


def test_pool_limits_set_the_environment_and_restore_it(monkeypatch):
    import cv2

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    monkeypatch.delenv("OPENCV_FOR_THREADS_NUM", raising=False)
    cv2_before = cv2.getNumThreads()
    with executors.thread_limits(pool=True):
        assert all(os.environ[v] == "1" for v in executors._THREAD_VARS)
        assert cv2.getNumThreads() == 1
    assert os.environ["OMP_NUM_THREADS"] == "3"
    assert "OPENCV_FOR_THREADS_NUM" not in os.environ
    assert cv2.getNumThreads() == cv2_before
    with executors.thread_limits(pool=False):  # one process: only BLAS is limited
        assert os.environ["OMP_NUM_THREADS"] == "3"


def _thread_state(_item):
    return os.environ.get("NUMBA_NUM_THREADS"), blas_threads()


def test_pool_workers_run_one_thread_and_the_parent_gets_its_own_back():
    before = blas_threads()
    results = list(executors.LocalExecutor(2).map(_thread_state, range(4)))
    for env, blas in results:
        assert env == "1" and all(n == 1 for n in blas)
    assert blas_threads() == before


def test_serial_runs_use_one_blas_thread_while_frames_run():
    if not blas_threads():
        pytest.skip("no OpenBLAS loaded in this process")
    results = list(executors.SerialExecutor().map(_thread_state, range(2)))
    assert all(all(n == 1 for n in blas) for _, blas in results)


# -- outputs against the code before issue 18 ----------------------------------------------------
#: sha256 of every depth map / cloud the commands wrote, by the code before issue 18.
DIGESTS = {
    "beams_kitti_multi": {
        "n1/000001.bin": "28ff42dff5880ac00c2a5ae1c6c66a5a33c3feece4d53d5ab11e57943be4a4af",
        "n16/000001.bin": "4cba2ab0a19b316b6f45ca3591d047a7866be8abf13e13f5b2a1c0f89afff428",
        "n2/000001.bin": "dd9983c550f146028e17f9a7de4eb917e36b241ce3b10c88a794717ffd90b26b",
        "n4/000001.bin": "4ba4406b2ecbc187a6203cab00769be02b08053165f78ea72b34b45426f66e78",
    },
    "beams_kitti_noprofile": {
        "n1/000001.bin": "28ff42dff5880ac00c2a5ae1c6c66a5a33c3feece4d53d5ab11e57943be4a4af",
        "n2/000001.bin": "dd9983c550f146028e17f9a7de4eb917e36b241ce3b10c88a794717ffd90b26b",
        "n3/000001.bin": "888c707c817bb8f8bc7ad311ad7701b921ba2e2ad118be6a26511e78714d0140",
        "n4/000001.bin": "4ba4406b2ecbc187a6203cab00769be02b08053165f78ea72b34b45426f66e78",
        "n8/000001.bin": "a785a1e6eae33915ccaf6e918b9f3db47c4286faf8ce410bc6e8842f40892546",
    },
    "beams_kitti_plpp": {
        "000001.bin": "1225ab5180519825ae8db637eeac886a98bd6c23b415247e94c0f053ea90f41b",
    },
    "beams_synth_4": {
        "000000.bin": "aec7f1f7a38e3ef98f66a2e5d686081b9bf5eda900746c83d35ad3a6a586009c",
        "000001.bin": "8acdb8ac01ae410a84a4e1c841f452a9d9a94d6977453ab72275cc0f6fc7b17d",
        "000002.bin": "afeb8a0135da2f23c4add3304c560e6aef7a6cb57a6b05170a98f9730fc7f481",
    },
    "jbf_synth": {
        "000000.png": "a38478e91d1e94fe2a27b6e0a0b23b26289cb3d09f4450ec23878d1f1c62fc29",
        "000000_conf.png": "6a0a3c40d68dd62a7a115b8f797e12d091ac48f7efe207858a21b97d2bcf2cda",
        "000001.png": "93e8e25bbc8ad9c562f9a4c4846569b263e278039da3897edf5ad65796c95f5c",
        "000001_conf.png": "b88e978da2948161b01547c7515e703deb2ae3433cd211f1958f700fd0c32cba",
        "000002.png": "4f0725d2983f38e98d3d587cba0973748e4cceca9fbc32ec7dfd6ce633a8dd12",
        "000002_conf.png": "cce850a49d00a3524f957cdb295d76d8d210311035cc9800dffe7e0b2dcb6bcb",
    },
    "jbf_synth_rgb_maxconf": {
        "000000.png": "b47b227b82221964e534d9844796b755d63d3c3b08efd1be3119381adcaca21a",
        "000000_conf.png": "da0c6032ea4ddbb938b982e68098b5803d66db02d2378b798c873d5bc964c829",
        "000001.png": "f823683f77cad2babe6975f61b77415de5930f85bb2f4dcf37551a65c2ad9d6d",
        "000001_conf.png": "f7be8f17aa3223f91c7285728c7c45b6c28d7c135b6e418fdb7cdb1fd44f53fe",
        "000002.png": "6d3037758ff10aa91c295247a163908c6aedeac336fcf1847de23758f82bdcf9",
        "000002_conf.png": "f0f34b0965f54ff1a8e3f24b2684753036897e874404fb180790c159a6248ee9",
    },
    "project_kitti_md2": {
        "000001.png": "624d9b2a99043a4ff6f1962d0ea17e24ecc75e4a81f2dedab23e9271806c40dc",
    },
    "project_radar": {
        "000000.png": "68bc90928d6da2b3045fec227d93c08ccb6367afb3f2fc292d1064db9bfd2131",
        "000001.png": "e0c966ed871d26ed7a0a44b3ec5e74c21786c6fadf692ce3480048ee5619d6b6",
        "000002.png": "935be54aba6542e31b58d0cd0a436f7423ebbf441c59c0f023f2ee861a5987bd",
    },
    "project_synth_npy_crop": {
        "000000.npy": "88c69427383f148d70c0c1aa01f272d522ec45cb44a0fe13ae57c175ec290893",
        "000001.npy": "1d8df1d6c4bba818d76245162df0316f18812077cc5d78123060d979201aabbf",
        "000002.npy": "8400fa34b72861464e5b5e9e387513a6886ed52d7271060912373d88af106963",
    },
    "project_synth_png": {
        "000000.png": "76dd4384d0519f7930703cbc9f5ba92a6ebf0350bf4d7d7b44e00724aff22750",
        "000001.png": "9ad00bf6088f6957821e23c238c2eb3565712f82e1ebc5fd57dbf9ebbbd75f8a",
        "000002.png": "e413220a9830fe3cba9d0b6eeec957f0949eb438ee47de2ae51107e77d761ea5",
    },
}

CASES = {
    "project_synth_png": ["project", SYNTH / "velodyne", "--calib", SYNTH / "calib",
                          "--image-size", "1242x375"],
    "project_synth_npy_crop": ["project", SYNTH / "velodyne", "--calib", SYNTH / "calib",
                               "--image-size", "1242x375", "--format", "npy", "--resize", "0.5",
                               "--crop", "20,10,150,600", "--max-depth", "60"],
    "project_kitti_md2": ["project", KITTI / "velodyne", "--calib", KITTI / "calib", "--image",
                          KITTI / "image_2", "--pixel-offset", "-1"],
    "project_radar": ["project", *sorted((SYNTH / "radar").glob("??????.pcd")), "--calib",
                      SYNTH / "calib_radar"],
    "beams_kitti_multi": ["beams", KITTI / "velodyne", "--n", "1,2,4,16"],
    "beams_kitti_noprofile": ["beams", KITTI / "velodyne", "--n", "1,2,3,4,8", "--profile",
                              "none", "--select", "horizon"],
    "beams_kitti_plpp": ["beams", KITTI / "velodyne", "--select", "pl++", "--n", "4", "--calib",
                         KITTI / "calib", "--image", KITTI / "image_2"],
    "beams_synth_4": ["beams", SYNTH / "velodyne", "--n", "4"],
}  # fmt: skip
JBF_CASES = {
    "jbf_synth": ["--confidence"],
    "jbf_synth_rgb_maxconf": ["--range-metric", "rgb", "--conflict", "max-confidence",
                              "--confidence"],
}  # fmt: skip


def digests(out: Path) -> dict[str, str]:
    return {
        p.relative_to(out).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(out.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.parts and p.suffix in (".png", ".npy", ".bin")
    }


def run(args) -> None:
    r = CliRunner().invoke(cli, ["-q", *map(str, args)])
    assert r.exit_code == 0, r.output


@pytest.mark.parametrize("case", sorted(CASES))
def test_outputs_are_the_bytes_of_the_code_before(case, tmp_path):
    run([*CASES[case], "-o", tmp_path / case])
    assert digests(tmp_path / case) == DIGESTS[case]


@pytest.mark.parametrize("case", sorted(JBF_CASES))
@pytest.mark.parametrize("workers", ["1", "2"])
def test_jbf_outputs_are_the_bytes_of_the_code_before(case, workers, tmp_path):
    radar = tmp_path / "radar"
    run([*CASES["project_radar"], "-o", radar])
    out = tmp_path / case
    run(["jbf-expand", radar, "--image", SYNTH / "image_2", "--calib", SYNTH / "calib_radar",
         "-o", out, "--workers", workers, *JBF_CASES[case]])  # fmt: skip
    assert digests(out) == DIGESTS[case]


def test_project_with_two_workers_writes_the_same_bytes(tmp_path):
    run([*CASES["project_synth_png"], "-o", tmp_path / "w2", "--workers", "2"])
    assert digests(tmp_path / "w2") == DIGESTS["project_synth_png"]


# -- start-up ------------------------------------------------------------------------------------

_PROBE = """
import sys
from sparsetools.cli.main import main
try:
    main(sys.argv[1:])
except SystemExit as exc:
    assert not exc.code, exc.code
heavy = ("numba", "torch", "sympy", "open3d", "pyarrow", "scipy", "dask", "concurrent.futures.process")
print("heavy:" + ",".join(m for m in heavy if m in sys.modules))
"""


def test_a_one_frame_project_run_loads_no_heavy_library(tmp_path):
    args = ["-q", "project", str(KITTI / "velodyne" / "000001.bin"), "--calib",
            str(KITTI / "calib" / "000001.txt"), "--image", str(KITTI / "image_2" / "000001.png"),
            "-o", str(tmp_path / "out")]  # fmt: skip
    r = subprocess.run([sys.executable, "-c", _PROBE, *args], capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "heavy:"  # none of them
    assert list((tmp_path / "out").glob("*.png"))


def test_pool_class_is_imported_when_first_needed():
    r = subprocess.run(
        [sys.executable, "-c", "import sys, sparsetools.pipeline.executors as ex; "
         "a = 'concurrent.futures.process' in sys.modules; ex.ProcessPoolExecutor; "
         "print(a, 'concurrent.futures.process' in sys.modules)"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.stdout.split() == ["False", "True"], r.stderr


# -- lowlight-synth: the flare bank from the on-disk cache ---------------------------------------


def lowlight_images(out: Path) -> dict[str, str]:
    return {k: v for k, v in digests(out).items() if not k.startswith("records/")}


def test_lowlight_outputs_do_not_depend_on_the_flare_bank_cache(tmp_path, monkeypatch):
    from sparsetools.io import flare_bank

    args = ["lowlight-synth", SYNTH / "image_2" / "000000.png", "--seed", "3", "--variants", "2"]
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the cache folder would be")
    monkeypatch.setenv("SPARSETOOLS_CACHE_DIR", str(blocked / "sub"))  # cannot be created
    run([*args, "-o", tmp_path / "memory"])
    cache = tmp_path / "cache"
    monkeypatch.setenv("SPARSETOOLS_CACHE_DIR", str(cache))
    flare_bank._cached.cache_clear()
    run([*args, "-o", tmp_path / "built"])  # builds the cache file
    files = list(cache.glob("flare-bank-*.npz"))
    assert len(files) == 1
    flare_bank._cached.cache_clear()
    run([*args, "-o", tmp_path / "loaded"])  # loads it
    files[0].write_bytes(b"not a zip")
    flare_bank._cached.cache_clear()
    run([*args, "-o", tmp_path / "rebuilt"])  # a broken cache is rebuilt, never fatal
    memory = lowlight_images(tmp_path / "memory")
    assert len(memory) == 2
    for name in ("built", "loaded", "rebuilt"):
        assert lowlight_images(tmp_path / name) == memory, name
