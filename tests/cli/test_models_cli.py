"""``edgerecon models``: where the person model is, and fetching it from a wheel."""

from __future__ import annotations

import json
import zipfile

from edgerecon.cli import main
from edgerecon.scene.people import PERSON_MODEL_FILE, PERSON_MODEL_MEMBER, models_dir


def test_models_lists_a_missing_model(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setenv("EDGERECON_MODELS", str(tmp_path / "m"))
    assert main(["models", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["models_dir"] == str(models_dir())
    assert info["person_model"]["present"] is False
    assert main(["models"]) == 0
    assert "not fetched; `edgerecon models fetch`" in capsys.readouterr().out


def test_fetch_refuses_a_wheel_whose_model_is_not_the_measured_one(tmp_path, capsys) -> None:
    wheel = tmp_path / "mediapipe-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl"
    with zipfile.ZipFile(wheel, "w") as zf:
        zf.writestr(PERSON_MODEL_MEMBER, b"something else")
    code = main(["models", "fetch", "--wheel", str(wheel), "--dir", str(tmp_path / "m")])
    assert code != 0
    assert "SHA-256" in capsys.readouterr().err
    assert not (tmp_path / "m" / PERSON_MODEL_FILE).exists()
