from controlgs_adapter.cli import main


def test_cli_reports_bad_input_without_traceback(capsys, tmp_path):
    assert main(["demo", "--resolution", "0", "--out", str(tmp_path / "unused")]) == 2
    err = capsys.readouterr().err
    assert "resolution" in err and "Traceback" not in err
