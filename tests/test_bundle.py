"""Damaged, edited and mismatched bundles: each is refused in one BundleError line, or (an edit
that changes nothing the model computes) loads and gives the intact bundle's numbers."""
import json
import logging
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from gyronet.model.baselines import TempPolynomial
from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import load_recording
from gyronet.errors import BundleError
from gyronet.bundle.io import read_bundle, save_bundle, sha256_file

ROOT = Path(__file__).resolve().parents[1]
N_ROWS = 400


@pytest.fixture(scope="module")
def columns(cycle_csv):
    recording = load_recording(cycle_csv)
    return {k: v[:N_ROWS] for k, v in recording.columns.items()}


@pytest.fixture(scope="module")
def reference(bundle, columns):
    return Compensator.load(bundle).process(columns).rate_dps


@pytest.fixture(scope="module")
def kalman_bundle(tmp_path_factory, paper_csv):
    """A tiny bundle with a Kalman stage."""
    from gyronet.training.dataset import DriftData
    from gyronet.model.rbf import RBFNet
    from gyronet.training.pipeline import train_run

    out = tmp_path_factory.mktemp("kalman_run")
    data = DriftData(str(paper_csv))
    model = RBFNet(data.n_features, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    train_run(data, model, None, out, {"max_epochs": 20, "progress": False},
              kalman_cfg={"enabled": True, "mode": "smooth", "q_rate_dps2_per_s": 0.01})
    return out / "compensator"


def _copy(src: Path, tmp_path: Path, name: str) -> Path:
    dst = tmp_path / name
    shutil.copytree(src, dst)
    return dst


def _edit_meta(path: Path, edit) -> None:
    meta = json.loads((path / "meta.json").read_text())
    edit(meta)
    (path / "meta.json").write_text(json.dumps(meta, indent=1))


def _unverified(meta: dict) -> None:
    """As a bundle written before checksums: no sha256 field (model.pt's own copy is kept)."""
    meta.pop("sha256", None)


def _outcome(path: Path, columns, reference) -> str:
    """'refused' (one line naming the bundle), 'same' (loads, same numbers) or 'WRONG'; others raise."""
    try:
        compensator = Compensator.load(path)
    except BundleError as err:
        message = str(err)
        assert "\n" not in message and str(path) in message, message
        return "refused"
    out = compensator.process(columns).rate_dps
    return "same" if np.array_equal(out, reference) else "WRONG"


def _file_damage(path: Path) -> dict:
    """Truncations and bit flips of model.pt, missing files."""
    size = (path / "model.pt").stat().st_size
    variants = {}
    for cut in (0, 1, 22, size // 3, size // 2, size - 22, size - 1):
        variants[f"model.pt truncated to {cut}"] = ("model.pt", lambda p, cut=cut: p.write_bytes(p.read_bytes()[:cut]))
    for offset in np.linspace(0, size - 1, 25).astype(int).tolist():
        def flip(p, offset=offset):
            data = bytearray(p.read_bytes())
            data[offset] ^= 0x10
            p.write_bytes(bytes(data))
        variants[f"model.pt bit flip at {offset}"] = ("model.pt", flip)
    variants["model.pt missing"] = ("model.pt", lambda p: p.unlink())
    variants["model.pt empty folder"] = ("model.pt", lambda p: (p.unlink(), p.mkdir()))
    variants["meta.json missing"] = ("meta.json", lambda p: p.unlink())
    for label, text in (("truncated", None), ("empty", b""), ("list", b"[]"), ("null", b"null"), ("number", b"3"),
                        ("binary", bytes(range(256))), ("utf16", json.dumps({"format": 1}).encode("utf-16"))):
        def write(p, text=text):
            p.write_bytes(p.read_bytes()[:len(p.read_bytes()) // 2] if text is None else text)
        variants[f"meta.json {label}"] = ("meta.json", write)
    return variants


META_FIELDS = ("format", "gyronet_version", "input_columns", "features", "feature_names", "fs_hz", "temp_range_c",
               "axes", "output", "data_sha256", "model", "kalman", "sha256")
WRONG_VALUES = [None, "abc", 0, -1, 1e308, True, [], {}, [1, 2], {"kind": "temp"}, float("nan")]


def _meta_edits() -> dict:
    edits = {}
    for field in META_FIELDS:
        edits[f"drop {field}"] = lambda m, f=field: m.pop(f)
        for value in WRONG_VALUES:
            edits[f"{field} = {value!r}"] = lambda m, f=field, v=value: m.__setitem__(f, v)
    edits.update({
        "format 99": lambda m: m.__setitem__("format", 99),
        "format '1'": lambda m: m.__setitem__("format", "1"),
        "gyronet_version 99": lambda m: m.__setitem__("gyronet_version", "99.0.0"),
        "fs_hz doubled": lambda m: m.__setitem__("fs_hz", m["fs_hz"] * 2),
        "fs_hz as int": lambda m: m.__setitem__("fs_hz", int(m["fs_hz"])),
        "features cut to temperature": lambda m: (m.__setitem__("features", m["features"][:1]),
                                                  m.__setitem__("feature_names", m["feature_names"][:1])),
        "features reordered": lambda m: m.__setitem__("features", m["features"][::-1]),
        "rate tau changed": lambda m: m["features"][1].__setitem__("tau_s", 2.0),
        "rate tau negative": lambda m: m["features"][1].__setitem__("tau_s", -5.0),
        "unknown feature kind": lambda m: m["features"][0].__setitem__("kind", "tmep"),
        "feature_names renamed": lambda m: m["feature_names"].__setitem__(0, "t"),
        "temp range reversed": lambda m: m.__setitem__("temp_range_c", m["temp_range_c"][::-1]),
        "temp range widened": lambda m: m.__setitem__("temp_range_c", [-100.0, 200.0]),
        "temp range 3 values": lambda m: m.__setitem__("temp_range_c", [1, 2, 3]),
        "axes reordered": lambda m: m.__setitem__("axes", ["z", "y", "x"]),
        "input column dropped": lambda m: m["input_columns"].remove("gyro_z_dps"),
        "model class poly": lambda m: m["model"].__setitem__("class", "TempPolynomial"),
        "kalman true without kalman.json": lambda m: m.__setitem__("kalman", True),
        "sha256 of model wrong": lambda m: m["sha256"].__setitem__("model.pt", "0" * 64),
        "sha256 not hex": lambda m: m["sha256"].__setitem__("model.pt", "xyz"),
        "extra field": lambda m: m.__setitem__("notes", "calibrated in chamber 2"),
        "version string edited": lambda m: m.__setitem__("gyronet_version", "0.1.1"),
        "output text edited": lambda m: m.__setitem__("output", "drift"),
    })
    return edits


HARMLESS_DROPS = {"gyronet_version", "output", "data_sha256", "model", "sha256", "kalman"}
# changes nothing the model computes: loads, same numbers (a bundle without sha256 warns that it cannot be verified)
HARMLESS_EDITS = {"extra field", "version string edited", "output text edited", "fs_hz as int",
                  "gyronet_version = 'abc'", "output = 'abc'", "data_sha256 = 'abc'", "model = {}",
                  "model = {'kind': 'temp'}", "sha256 = {}",
                  *(f"drop {f}" for f in HARMLESS_DROPS)}
MUST_REFUSE = {"format 99", "gyronet_version 99", "fs_hz doubled", "features cut to temperature", "rate tau changed",
               "axes reordered", "model class poly", "kalman true without kalman.json", "sha256 of model wrong",
               "drop features", "drop fs_hz", "drop temp_range_c", "temp range widened", "input column dropped"}


def test_damaged_files_are_refused_in_one_line(bundle, columns, reference, tmp_path):
    outcomes = {}
    for i, (label, (name, damage)) in enumerate(_file_damage(bundle).items()):
        path = _copy(bundle, tmp_path, f"b{i}")
        damage(path / name)
        outcomes[label] = _outcome(path, columns, reference)
    assert set(outcomes.values()) == {"refused"}, outcomes
    assert len(outcomes) >= 40


def test_edited_meta_is_refused_or_harmless(bundle, columns, reference, tmp_path):
    outcomes = {}
    for i, (label, edit) in enumerate(_meta_edits().items()):
        path = _copy(bundle, tmp_path, f"b{i}")
        try:
            _edit_meta(path, edit)
        except (ValueError, TypeError):  # NaN written as JSON by json.dumps is still JSON to us
            continue
        outcomes[label] = _outcome(path, columns, reference)
    assert "WRONG" not in outcomes.values(), {k: v for k, v in outcomes.items() if v == "WRONG"}
    assert {k for k, v in outcomes.items() if v == "same"} == HARMLESS_EDITS
    assert MUST_REFUSE <= {k for k, v in outcomes.items() if v == "refused"}
    assert len(outcomes) > 150


def test_unverified_bundle_checks_what_it_can(bundle, columns, reference, tmp_path):
    """Without checksums (an old bundle) the schema, the saved training fields and the probe still hold."""
    outcomes = {}
    for i, (label, edit) in enumerate(_meta_edits().items()):
        path = _copy(bundle, tmp_path, f"b{i}")
        try:
            _edit_meta(path, lambda m: (edit(m), _unverified(m)))
        except (ValueError, TypeError, KeyError):
            continue
        outcomes[label] = _outcome(path, columns, reference)
    assert "WRONG" not in outcomes.values(), {k: v for k, v in outcomes.items() if v == "WRONG"}
    assert MUST_REFUSE - {"sha256 of model wrong"} <= {k for k, v in outcomes.items() if v == "refused"}


def _strip_trained_copy(path: Path) -> None:
    """Re-save model.pt without its copy of the training fields and drop the checksums: a pre-change bundle."""
    model = torch.jit.load(str(path / "model.pt"))
    model.save(str(path / "model.pt"))
    _edit_meta(path, _unverified)


def test_bundle_from_before_checksums_loads_with_one_warning(bundle, columns, reference, tmp_path, caplog):
    path = _copy(bundle, tmp_path, "old")
    _strip_trained_copy(path)
    with caplog.at_level(logging.WARNING):
        out = Compensator.load(path).process(columns).rate_dps
    np.testing.assert_array_equal(out, reference)
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "cannot be verified" in warnings[0].getMessage()


def test_old_bundle_with_mismatched_model_is_refused(bundle, columns, reference, tmp_path):
    """No checksums to lean on: the model's own width and class are checked against meta.json."""
    cut = _copy(bundle, tmp_path, "cut")
    _strip_trained_copy(cut)
    _edit_meta(cut, lambda m: (m.__setitem__("features", m["features"][:1]),
                               m.__setitem__("feature_names", m["feature_names"][:1])))
    with pytest.raises(BundleError, match="takes 3 inputs, but meta.json lists 1 features"):
        Compensator.load(cut)
    poly = _copy(bundle, tmp_path, "poly")
    _strip_trained_copy(poly)
    torch.jit.script(TempPolynomial(3)).save(str(poly / "model.pt"))
    with pytest.raises(BundleError, match="model.pt is a TempPolynomial, but meta.json describes a RBFNet"):
        Compensator.load(poly)


def test_model_from_another_bundle_is_refused(bundle, tmp_path):
    """A poly3 model.pt dropped into a default bundle (issue 10: used silently)."""
    meta = json.loads((bundle / "meta.json").read_text())
    other = tmp_path / "poly3"
    poly = TempPolynomial(3)
    poly.fit_closed_form(torch.randn(50, 3, dtype=torch.float64) + 20, torch.randn(50, 3, dtype=torch.float64))
    save_bundle(poly, {k: v for k, v in meta.items() if k not in ("format", "gyronet_version", "kalman", "sha256")},
                other)
    mixed = _copy(bundle, tmp_path, "mixed")
    shutil.copy(other / "model.pt", mixed / "model.pt")
    with pytest.raises(BundleError, match="model.pt: checksum differs"):
        Compensator.load(mixed)


def test_a_run_folder_given_as_the_bundle_names_its_bundle(bundle, tmp_path):
    """model=outputs/train/RUN (the run's folder, not its compensator/) is the commonest slip."""
    run = bundle.parent  # the folder train.py wrote, holding compensator/
    with pytest.raises(BundleError, match=f"not a compensator bundle \\(no model.pt\\); did you mean {bundle}\\?"):
        Compensator.load(run)
    with pytest.raises(BundleError, match=r"\(no model.pt\)$"):
        Compensator.load(tmp_path)


def test_new_bundle_records_checksums(bundle):
    meta = json.loads((bundle / "meta.json").read_text())
    assert meta["sha256"] == {"model.pt": sha256_file(bundle / "model.pt")}
    assert read_bundle(bundle).verified


def test_the_same_model_saved_twice_is_the_same_file(tmp_path):
    """A repeated run can be checked by its checksums (the archive was named after the temporary file)."""
    poly = TempPolynomial(3)
    poly.fit_closed_form(torch.randn(50, 3, dtype=torch.float64) + 20, torch.randn(50, 3, dtype=torch.float64))
    for name in ("a", "b"):
        save_bundle(poly, {}, tmp_path / name)
    assert (tmp_path / "a" / "model.pt").read_bytes() == (tmp_path / "b" / "model.pt").read_bytes()


def test_kalman_stage_present_iff_meta_says_so(kalman_bundle, columns, tmp_path):
    reference = Compensator.load(kalman_bundle).process(columns).rate_dps
    meta = json.loads((kalman_bundle / "meta.json").read_text())
    assert meta["kalman"] is True and set(meta["sha256"]) == {"model.pt", "kalman.json"}
    kalman = json.loads((kalman_bundle / "kalman.json").read_text())
    variants = {
        "kalman.json missing": lambda p: (p / "kalman.json").unlink(),
        "meta kalman false": lambda p: _edit_meta(p, lambda m: m.__setitem__("kalman", False)),
        "kalman.json truncated": lambda p: (p / "kalman.json").write_text((p / "kalman.json").read_text()[:100]),
        "kalman.json edited": lambda p: (p / "kalman.json").write_text(json.dumps({**kalman, "mode": "rate"})),
    }
    broken_stage = {
        "no model": {k: v for k, v in kalman.items() if k != "model"},
        "bad mode": {**kalman, "mode": "fast"},
        "q negative": {**kalman, "q_rate_dps2_per_s": -1},
        "q text": {**kalman, "q_rate_dps2_per_s": "x"},
        "version 99": {**kalman, "version": 99},
        "model a list": {**kalman, "model": []},
        "axes missing": {**kalman, "model": {k: v for k, v in kalman["model"].items() if k != "axes"}},
        "other rate": {**kalman, "model": {**kalman["model"], "fs_hz": 7.0}},
        "not an object": [1, 2],
    }
    for label, data in broken_stage.items():
        def write(p, data=data):
            (p / "kalman.json").write_text(json.dumps(data))
            _edit_meta(p, lambda m: m["sha256"].__setitem__("kalman.json", sha256_file(p / "kalman.json")))
        variants[f"checksummed {label}"] = write
    outcomes = {}
    for i, (label, damage) in enumerate(variants.items()):
        path = _copy(kalman_bundle, tmp_path, f"k{i}")
        damage(path)
        outcomes[label] = _outcome(path, columns, reference)
    assert set(outcomes.values()) == {"refused"}, outcomes
    plain = _copy(kalman_bundle, tmp_path, "plain")
    (plain / "kalman.json").unlink()
    with pytest.raises(BundleError, match="kalman: true, but kalman.json is missing"):
        Compensator.load(plain)


def test_compensate_refuses_damaged_bundle_in_one_line(bundle, cycle_csv, tmp_path):
    path = _copy(bundle, tmp_path, "damaged")
    data = bytearray((path / "model.pt").read_bytes())
    data[len(data) // 2] ^= 1
    (path / "model.pt").write_bytes(bytes(data))
    out = tmp_path / "o.csv"
    proc = subprocess.run([sys.executable, "scripts/compensate.py", f"model={path}", f"input={cycle_csv}",
                           f"output={out}", f"hydra.run.dir={tmp_path / 'hydra'}"], cwd=ROOT, capture_output=True,
                          text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("error: ") and proc.stderr.strip().count("\n") == 0
    assert "model.pt: checksum differs" in proc.stderr and not out.exists()


def test_torch_deprecating_torchscript_adds_nothing_to_stderr(torch_jit_warns, bundle, columns, tmp_path):
    """Every command loads or saves a bundle: torch 2.14's two lines a call would bury its one-line error."""
    from gyronet.bundle.io import load_unfrozen

    with pytest.warns(FutureWarning, match="torch.jit.script"):  # the stand-in warns as torch 2.14 does
        torch.jit.script(TempPolynomial(3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        save_bundle(TempPolynomial(3), {}, tmp_path / "poly")
        load_unfrozen(tmp_path / "poly")
        assert np.isfinite(Compensator.load(bundle).process(columns).rate_dps).all()


def test_a_deployment_says_its_kalman_stage_low_passes(kalman_bundle, bundle):
    from gyronet.bundle.offline import kalman_line

    line = kalman_line(Compensator.load(kalman_bundle))
    assert line.startswith("Kalman stage on: the output follows a rate step 50 % after ") and "x/y/z" in line
    assert kalman_line(Compensator.load(bundle)) is None
