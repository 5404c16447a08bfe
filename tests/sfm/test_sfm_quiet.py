"""Issue 46: COLMAP's own log is off at the default log level, counted in the report, shown with --log-level debug;
and no numpy scalar reprs (``np.float64(``) in what the CLI prints."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.io import read_json

GLOG_LINE = re.compile(r"^[IWE]\d{8} ", re.MULTILINE)
runner = CliRunner()


def _sfm(args: list[str], capfd: pytest.CaptureFixture[str]) -> str:
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    try:
        res = runner.invoke(app, args)
    finally:  # --log-level reconfigures the root logger for the whole test process
        root.handlers[:] = handlers
        root.setLevel(level)
    captured = capfd.readouterr()
    assert res.exit_code == 0, res.output + captured.err
    return res.output + captured.out + captured.err


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_colmap_log_is_quiet_by_default_and_counted(five_frames: Path, tmp_path: Path, mapper: str,
                                                     capfd: pytest.CaptureFixture[str]):
    out = tmp_path / "sfm"
    text = _sfm(["sfm", str(five_frames), "--out", str(out), "--preset", "fast", "--set", "num_threads=1",
                 "--set", f"mapper.kind={mapper}"], capfd)
    assert not GLOG_LINE.search(text), text
    assert "np.float64(" not in text and "np.float32(" not in text
    assert "registered" in text  # the stage's own summary is still printed
    said = read_json(out / "sfm_report.json")["colmap_log"]
    assert said["shown_not_counted"] is False
    assert said["warnings"] >= 0 and said["errors"] == 0


def test_colmap_log_is_shown_with_log_level_debug(five_frames: Path, tmp_path: Path,
                                                  capfd: pytest.CaptureFixture[str]):
    out = tmp_path / "sfm"
    text = _sfm(["--log-level", "debug", "sfm", str(five_frames), "--out", str(out), "--preset", "fast",
                 "--set", "num_threads=1"], capfd)
    lines = GLOG_LINE.findall(text)
    assert len(lines) > 10, text[-2000:]
    assert "feature_extraction" in text
    assert read_json(out / "sfm_report.json")["colmap_log"]["shown_not_counted"] is True


def test_glog_text_is_counted_by_severity_with_distinct_examples():
    from cadalign.sfm.colmap_log import ColmapLog, summed

    said = ColmapLog()
    said.add_text("I20261129 04:03:15.357067 1 sift.cc:764] Creating SIFT CPU feature extractor\n"
                  "W20261129 04:03:15.356272 1 feature_extraction.cc:445] Your current options use the maximum\n"
                  "W20261129 04:03:16.356272 1 feature_extraction.cc:445] Your current options use the maximum\n"
                  "    Residuals : 2000\n"
                  "E20261129 04:03:17.000000 1 incremental_pipeline.cc:1] No good initial image pair found.\n")
    assert (said.warnings, said.errors) == (2, 1)
    assert said.examples == ["Your current options use the maximum", "No good initial image pair found."]
    total = summed([said.to_json(), said.to_json(), {}])
    assert (total["warnings"], total["errors"], len(total["examples"])) == (4, 2, 2)
