"""load_mat (MATLAB v5 and v7.3) and DANNCE cameras written in both versions."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
import scipy.io

from freipose.geometry import CameraRig
from freipose.io.calibration import load_calibration
from freipose.io.matlab import MatFileError, load_mat
from freipose.testing import make_circle_rig


# -- a minimal MATLAB v7.3 writer (the HDF5 layout MATLAB's save -v7.3 produces) --------
class _V73:
    def __init__(self, path: Path):
        self.f = h5py.File(path, "w", userblock_size=512)
        self.refs = self.f.create_group("#refs#")
        self.n = 0
        self.path = path

    def _ref_target(self, value: Any) -> Any:
        self.n += 1
        return self.put(self.refs, f"r{self.n}", value)

    def put(self, parent: Any, name: str, value: Any) -> Any:
        if isinstance(value, dict):
            g = parent.create_group(name)
            g.attrs["MATLAB_class"] = np.bytes_("struct")
            fields = np.empty(len(value), dtype=object)
            for i, k in enumerate(value):
                fields[i] = np.array(list(k), dtype="S1")
            g.attrs.create("MATLAB_fields", fields, dtype=h5py.vlen_dtype(np.dtype("S1")))
            for k, v in value.items():
                self.put(g, k, v)
            return g
        if isinstance(value, str):
            d = parent.create_dataset(name, data=np.array([[ord(c)] for c in value], np.uint16))
            d.attrs["MATLAB_class"] = np.bytes_("char")
            d.attrs["MATLAB_int_decode"] = 2
            return d
        if isinstance(value, list):  # a column cell array
            refs = np.array([[self._ref_target(v).ref for v in value]], dtype=h5py.ref_dtype)
            d = parent.create_dataset(name, data=refs)  # MATLAB (n, 1) stored as (1, n)
            d.attrs["MATLAB_class"] = np.bytes_("cell")
            return d
        arr = np.atleast_2d(np.asarray(value, dtype=np.float64))
        d = parent.create_dataset(name, data=arr.T)
        d.attrs["MATLAB_class"] = np.bytes_("double")
        return d

    def close(self) -> None:
        self.f.close()
        with open(self.path, "r+b") as fh:
            fh.write(b"MATLAB 7.3 MAT-file, written by the FreiPose tests".ljust(116, b" "))


def _dannce_params(rig: CameraRig) -> list[dict[str, np.ndarray]]:
    """DANNCE params: MATLAB row-vector convention (K and r transposed)."""
    out = []
    for c in rig:
        k1, k2, p1, p2, k3 = c.dist
        out.append(
            {
                "K": c.K.T.copy(),
                "RDistort": np.array([[k1, k2, k3]]),
                "TDistort": np.array([[p1, p2]]),
                "r": c.R.T.copy(),
                "t": c.t.reshape(1, 3),
            }
        )
    return out


def _skew_rig() -> CameraRig:
    rig = make_circle_rig(3, distortion=True)
    cams = [
        c.replace(K=c.K + np.array([[0, -4.0 + 3 * i, 0], [0, 0, 0], [0, 0, 0]]))
        for i, c in enumerate(rig)
    ]
    return CameraRig(tuple(cams))


def _write_v5(path: Path, rig: CameraRig, names: bool = True) -> None:
    params = np.empty((len(rig), 1), dtype=object)
    for i, p in enumerate(_dannce_params(rig)):
        params[i, 0] = p
    data: dict[str, Any] = {"params": params}
    if names:
        cn = np.empty((1, len(rig)), dtype=object)
        for i, n in enumerate(rig.names):
            cn[0, i] = n
        data["camnames"] = cn
    scipy.io.savemat(path, data)


def _write_v73(path: Path, rig: CameraRig) -> None:
    w = _V73(path)
    w.put(w.f, "params", _dannce_params(rig))
    w.put(w.f, "camnames", list(rig.names))
    w.put(w.f, "info", {"note": "hello", "n": 3.0, "nested": {"x": [1.0, 2.0]}})
    w.close()


@pytest.mark.parametrize("version", ["v5", "v73"])
def test_dannce_cameras_both_mat_versions(tmp_path, version):
    rig = _skew_rig()
    p = tmp_path / "label3d_dannce.mat"
    (_write_v5 if version == "v5" else _write_v73)(p, rig)
    back = load_calibration(p)
    assert back.names == rig.names
    for a, b in zip(rig, back):
        for f in ("K", "dist", "R", "t"):
            np.testing.assert_allclose(getattr(b, f), getattr(a, f), atol=1e-12)
        assert b.K[0, 1] != 0
    assert back.metadata["units"] == "mm"


def test_dannce_default_camera_names(tmp_path):
    p = tmp_path / "cams.mat"
    _write_v5(p, _skew_rig(), names=False)
    assert load_calibration(p).names == ["Camera1", "Camera2", "Camera3"]


def test_load_mat_same_structure_for_v5_and_v73(tmp_path):
    rig = _skew_rig()
    _write_v5(tmp_path / "a.mat", rig)
    _write_v73(tmp_path / "b.mat", rig)
    a, b = load_mat(tmp_path / "a.mat"), load_mat(tmp_path / "b.mat")
    assert a["camnames"] == b["camnames"] == rig.names
    assert isinstance(a["params"], list) and isinstance(b["params"], list)
    for pa, pb in zip(a["params"], b["params"]):
        assert set(pa) == set(pb) == {"K", "RDistort", "TDistort", "r", "t"}
        for k in pa:
            assert pa[k].shape == pb[k].shape  # MATLAB shapes, e.g. t is (1, 3)
            np.testing.assert_allclose(pa[k], pb[k])
    info = b["info"]
    assert info["note"] == "hello" and info["n"].shape == (1, 1)
    assert [float(v[0, 0]) for v in info["nested"]["x"]] == [1.0, 2.0]  # a cell of scalars


def test_load_mat_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_mat(tmp_path / "none.mat")
    bad = tmp_path / "bad.mat"
    bad.write_bytes(b"this is not a mat file at all" * 10)
    with pytest.raises(MatFileError, match="not a readable MATLAB"):
        load_mat(bad)


def test_load_mat_real_dannce_labels(shared_data):
    m = load_mat(
        shared_data / "dannce-markerless-mouse" / "markerless_mouse_2" / "label3d_dannce.mat"
    )
    assert len(m["labelData"]) == 6 and m["labelData"][0]["data_2d"].shape == (91, 44)
    assert m["labelData"][0]["data_frame"].shape == (1, 91)
    skel = load_mat(shared_data / "dannce-markerless-mouse" / "mouse22_skeleton.mat")
    assert skel["joint_names"][:3] == ["EarL", "EarR", "Snout"] and skel["joints_idx"].shape == (
        24,
        2,
    )
