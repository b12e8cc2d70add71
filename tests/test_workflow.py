"""Declarative pipeline configs: parsing, variables, reports, failures."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.cli.pipeline import run_command
from sparsetools.errors import FormatError, ParameterError
from sparsetools.pipeline.workflow import load_workflow, run_workflow

CONFIG = """
name: tiny
vars:
  frames: "1"
  scene: ${out}/scene
steps:
  - name: scene
    run: synth-scene -o ${scene} --frames ${frames} --image-size 64x24 --underwater-frames 0 --seed 3
  - name: again
    run: [sparsetools, synth-scene, -o, "${scene}", --frames, "${frames}", --image-size, 64x24, --underwater-frames, "0", --seed, "3", --overwrite]
"""


def test_variables_and_both_run_forms(tmp_path):
    (tmp_path / "c.yaml").write_text(CONFIG)
    wf = load_workflow(tmp_path / "c.yaml", out_dir=tmp_path / "o", overrides={"frames": "2"})
    assert wf.steps[1].run == [*wf.steps[0].run, "--overwrite"]
    assert wf.steps[0].run[:3] == ["synth-scene", "-o", str(tmp_path / "o" / "scene")]
    assert wf.steps[0].run[4] == "2"


def test_toml_config(tmp_path):
    (tmp_path / "c.toml").write_text(
        'name = "t"\n[[steps]]\nname = "a"\nrun = "synth-scene -o ${out}/x"\n'
    )
    wf = load_workflow(tmp_path / "c.toml", out_dir="O")
    assert wf.steps[0].run == ["synth-scene", "-o", "O/x"]


@pytest.mark.parametrize(
    "text, message",
    [
        ("name: x\n", "non-empty 'steps'"),
        ("steps:\n  - name: a\n", "needs a 'run'"),
        ("steps: [ {run: 'x ${nope}'} ]\n", "unknown variable"),
        ("steps: [unclosed\n", "invalid config"),
    ],
)
def test_bad_configs(tmp_path, text, message):
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises((FormatError, ParameterError), match=message):
        load_workflow(tmp_path / "c.yaml", out_dir=tmp_path)


def test_run_writes_report_and_stops_at_failure(tmp_path):
    (tmp_path / "c.yaml").write_text(
        CONFIG + "  - name: broken\n    run: synth-scene -o ${out}/bad --frames 0\n"
        "  - name: never\n    run: synth-scene -o ${out}/never\n"
    )
    wf = load_workflow(tmp_path / "c.yaml", out_dir=tmp_path / "o")
    with pytest.raises(ParameterError, match="step 'broken' failed"):
        run_workflow(wf, tmp_path / "o", run_command=run_command, echo=lambda s: None)
    report = (tmp_path / "o" / "report.md").read_text()
    assert "## scene" in report and "## broken" in report and "## never" not in report
    assert (tmp_path / "o" / "scene" / "velodyne" / "000000.bin").is_file()
    assert not (tmp_path / "o" / "never").exists()


def test_cli_pipeline_missing_config_is_one_line(tmp_path):
    r = CliRunner().invoke(
        cli, ["pipeline", str(tmp_path / "none.yaml"), "-o", str(tmp_path / "o")]
    )
    assert r.exit_code == 1
    assert r.stderr.strip().startswith("Error:") and len(r.stderr.strip().splitlines()) == 1


def test_a_yaml_config_without_pyyaml_names_the_extra(tmp_path, monkeypatch):
    """PyYAML is the optional extra ``sparsetools[yaml]``: without it a YAML config is refused
    in one line naming the extra and TOML, nothing written; a TOML config still runs."""
    import sys

    monkeypatch.setitem(sys.modules, "yaml", None)  # `import yaml` raises ImportError
    (tmp_path / "c.yaml").write_text(CONFIG)
    r = CliRunner().invoke(cli, ["pipeline", str(tmp_path / "c.yaml"), "-o", str(tmp_path / "o")])
    assert r.exit_code == 1, r.output
    err = r.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in r.output
    assert "pip install 'sparsetools[yaml]'" in err and "TOML" in err and "c.yaml" in err
    assert not (tmp_path / "o").exists()
    (tmp_path / "c.toml").write_text(
        'name = "t"\n[[steps]]\nname = "a"\nrun = "synth-scene -o ${out}/x"\n'
    )
    assert load_workflow(tmp_path / "c.toml", out_dir="O").steps[0].run[:2] == ["synth-scene", "-o"]
