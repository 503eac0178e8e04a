"""``torchiid export-onnx``: the feature extractor written as an ONNX model."""

import pytest

from torchiid.cli import main


def test_export_onnx_takes_output_like_the_other_subcommands(tmp_path, monkeypatch, capsys):
    from pathlib import Path

    import torchiid.features.onnx_backend as onnx_backend
    from torchiid.cli import build_parser

    parser = build_parser()
    for flag in ("-o", "--output"):
        assert parser.parse_args(["export-onnx", flag, "models"]).output == Path("models")
    assert parser.parse_args(["export-onnx"]).output is None
    with pytest.raises(SystemExit):
        parser.parse_args(["export-onnx", "--output-dir", "models"])
    capsys.readouterr()
    written = []
    monkeypatch.setattr(onnx_backend, "export_to_dir", lambda d: written.append(d) or d / "m.onnx")
    assert main(["export-onnx", "-o", str(tmp_path)]) == 0
    assert written == [tmp_path]
    assert f"wrote {tmp_path / 'm.onnx'}" in capsys.readouterr().out
