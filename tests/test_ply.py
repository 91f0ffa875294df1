"""The 3DGS PLY layout (adapters/ply.py), checked with plyfile directly, not with our reader."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from mvgs_plugin.adapters import ply

N = 5


def known_gaussians(n=N, degree=3):
    """Attributes whose every value is distinct and encodes where it belongs."""
    k = (degree + 1) ** 2 - 1
    i = torch.arange(n, dtype=torch.float32)[:, None]
    means = i * 10 + torch.tensor([0.1, 0.2, 0.3])
    sh0 = (i * 10 + torch.tensor([0.4, 0.5, 0.6]))[:, None, :]
    # shN[n, k, c] = 1000 n + 10 k + c: the file position of each value is then checkable
    shN = (1000 * torch.arange(n)[:, None, None] + 10 * torch.arange(k)[None, :, None]
           + torch.arange(3)[None, None, :]).float()
    opac = i[:, 0] * 10 + 0.7
    scales = i * 10 - torch.tensor([1.0, 2.0, 3.0])
    quats = i * 10 + torch.tensor([1.5, 2.5, 3.5, 4.5])
    return dict(means=means, sh0=sh0, shN=shN, opacities=opac, scales=scales, quats=quats)


def write(path, g):
    ply.write_gaussian_ply(path, g["means"], g["sh0"], g["shN"], g["opacities"], g["scales"], g["quats"])


def expected_names(degree):
    n_rest = 3 * ((degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


@pytest.mark.parametrize("degree", [0, 3])
def test_layout_read_with_plyfile(tmp_path, degree):
    g = known_gaussians(degree=degree)
    path = tmp_path / "model.ply"
    write(path, g)
    data = PlyData.read(str(path))
    assert [el.name for el in data.elements] == ["vertex"]
    assert not data.text and data.byte_order == "<"
    v = data["vertex"].data
    assert list(v.dtype.names) == expected_names(degree)
    assert all(v.dtype[name] == np.dtype("<f4") for name in v.dtype.names)
    assert len(v) == N
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), g["means"].numpy())
    np.testing.assert_array_equal(np.stack([v["nx"], v["ny"], v["nz"]], 1), np.zeros((N, 3)))
    np.testing.assert_array_equal(np.stack([v[f"f_dc_{c}"] for c in range(3)], 1), g["sh0"][:, 0].numpy())
    k = (degree + 1) ** 2 - 1
    for c in range(3):  # channel-major: f_rest_{c*K'+j} is coefficient j of channel c
        for j in range(k):
            np.testing.assert_array_equal(v[f"f_rest_{c * k + j}"], 1000 * np.arange(N) + 10 * j + c)
    np.testing.assert_array_equal(v["opacity"], g["opacities"].numpy())
    np.testing.assert_array_equal(np.stack([v[f"scale_{i}"] for i in range(3)], 1), g["scales"].numpy())
    np.testing.assert_array_equal(np.stack([v[f"rot_{i}"] for i in range(4)], 1), g["quats"].numpy())


def test_round_trip(tmp_path):
    g = known_gaussians()
    path = tmp_path / "model.ply"
    write(path, g)
    back = ply.read_gaussian_ply(path)
    assert back.sh_degree == 3
    for name, value in g.items():
        got = getattr(back, name)
        assert got.dtype == torch.float32
        assert torch.equal(got, value), name


def test_reads_other_tools_order_and_types(tmp_path):
    """Properties by name, in any order and type (here float64, shuffled, no normals, extras)."""
    g = known_gaussians(degree=1)
    names = [n for n in expected_names(1) if n not in ("nx", "ny", "nz")] + ["extra"]
    rng = np.random.default_rng(0)
    order = list(rng.permutation(names))
    values = {"x": g["means"][:, 0], "y": g["means"][:, 1], "z": g["means"][:, 2],
              "opacity": g["opacities"], "extra": torch.zeros(N)}
    values.update({f"f_dc_{c}": g["sh0"][:, 0, c] for c in range(3)})
    values.update({f"f_rest_{c * 3 + j}": g["shN"][:, j, c] for c in range(3) for j in range(3)})
    values.update({f"scale_{i}": g["scales"][:, i] for i in range(3)})
    values.update({f"rot_{i}": g["quats"][:, i] for i in range(4)})
    arr = np.empty(N, dtype=[(n, "f8") for n in order])
    for n in order:
        arr[n] = values[n].numpy()
    path = tmp_path / "other.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    back = ply.read_gaussian_ply(path)
    assert back.sh_degree == 1
    for name, value in g.items():
        assert torch.equal(getattr(back, name), value), name


def test_missing_property_is_named(tmp_path):
    names = [n for n in expected_names(0) if n != "scale_1"]
    arr = np.zeros(3, dtype=[(n, "f4") for n in names])
    path = tmp_path / "bad.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))
    with pytest.raises(ValueError, match="'scale_1'"):
        ply.read_gaussian_ply(path)


def test_f_rest_gap_and_bad_count_are_named(tmp_path):
    names = expected_names(1)
    gap = [n for n in names if n != "f_rest_4"]
    path = tmp_path / "gap.ply"
    PlyData([PlyElement.describe(np.zeros(2, dtype=[(n, "f4") for n in gap]), "vertex")]).write(str(path))
    with pytest.raises(ValueError, match="f_rest_4"):
        ply.read_gaussian_ply(path)
    six = [n for n in names if n not in ("f_rest_6", "f_rest_7", "f_rest_8")]
    PlyData([PlyElement.describe(np.zeros(2, dtype=[(n, "f4") for n in six]), "vertex")]).write(str(path))
    with pytest.raises(ValueError, match="6 f_rest"):
        ply.read_gaussian_ply(path)


def test_write_rejects_bad_shapes_and_nan(tmp_path):
    g = known_gaussians()
    with pytest.raises(ValueError, match="scales"):
        ply.write_gaussian_ply(tmp_path / "a.ply", g["means"], g["sh0"], g["shN"], g["opacities"],
                               g["scales"][:, :2], g["quats"])
    g["means"][2, 1] = float("nan")
    with pytest.raises(ValueError, match="means.*row 2"):
        write(tmp_path / "a.ply", g)
    assert not os.listdir(tmp_path)


def test_failed_write_leaves_existing_file_untouched(tmp_path, monkeypatch):
    path = tmp_path / "model.ply"
    write(path, known_gaussians(n=3))
    before = path.read_bytes()

    def half_then_fail(f, rows):
        f.write(rows[: len(rows) // 2].tobytes())
        raise OSError("disk full")

    monkeypatch.setattr(ply, "_write_rows", half_then_fail)
    with pytest.raises(OSError, match="disk full"):
        write(path, known_gaussians(n=40))
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["model.ply"]  # the temporary file is gone too
