"""MVGSConfig's MVAD and CRD groups (MVADConfig, CRDConfig), and the flat names of earlier
releases they replace, which keep working for one release with a DeprecationWarning."""

from __future__ import annotations

import dataclasses
import json
import warnings

import pytest

from mvgs_plugin import CRDConfig, MVADConfig, MVGSConfig, Stage


def test_presets_set_the_groups_as_documented():
    paper = MVGSConfig.paper()
    assert paper.mvad == MVADConfig(enabled=True, center="origin")
    assert paper.crd == CRDConfig(enabled=True, window_per_level=False, forward_only=False, max_miss=None,
                                  pad_by_miss=False, min_angle_deg=0.0, clip=False, max_new=None)
    # cross-ray densification is on in paper() only (it cloned ~nothing with its guards, issue 27)
    assert MVGSConfig.multiview().mvad == MVADConfig(enabled=True)
    for cfg in (MVGSConfig.default(), MVGSConfig.baseline(), MVGSConfig(), MVGSConfig.multiview()):
        assert cfg.crd == CRDConfig() and not cfg.crd.enabled
    for cfg in (MVGSConfig.default(), MVGSConfig.baseline(), MVGSConfig()):
        assert cfg.mvad == MVADConfig() and cfg.crd == CRDConfig() and not cfg.mvad.enabled and not cfg.crd.enabled


def test_round_trip_through_json_keeps_every_group_field():
    cfg = MVGSConfig.paper(crd=CRDConfig(enabled=True, window=(7, 9), max_new=0.5), mvad=MVADConfig(tau=0.3, rule=0.5))
    back = MVGSConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg and back.crd.window == (7, 9) and back.mvad.rule == 0.5


def test_the_flat_layout_of_earlier_checkpoints_loads():
    """A config dict as earlier releases wrote it (flat mvad_* / crd_* keys, mvad and crd as
    bools, max_views_rule) reads back as the same settings, written out by hand here."""
    old = {"stages": [{"factor": 2, "views": 4, "steps": 10}, {"factor": 1, "views": 2, "steps": 20}],
           "max_views_rule": "cap", "mvad": True, "mvad_tau": 0.8, "mvad_rule": "any", "mvad_rotation_weight": 0.0,
           "mvad_center": "origin", "crd": False, "crd_window": [10, 30], "crd_window_per_level": False,
           "crd_forward_only": True, "crd_max_miss": None, "crd_pad_by_miss": False, "crd_min_angle_deg": 2.0,
           "crd_clip": True, "crd_max_new": 0.1, "seed": 3}
    cfg = MVGSConfig.from_dict(old)
    assert cfg.stages == (Stage(2, 4, 10), Stage(1, 2, 20)) and cfg.seed == 3
    assert cfg.mvad == MVADConfig(enabled=True, tau=0.8, center="origin")
    assert cfg.crd == CRDConfig(enabled=False, window=(10, 30), window_per_level=False, max_miss=None,
                                pad_by_miss=False, min_angle_deg=2.0, max_new=0.1)


def test_flat_keywords_and_reads_warn_and_merge_into_the_groups():
    with pytest.warns(DeprecationWarning, match="mvad_tau -> mvad.tau"):
        cfg = MVGSConfig.paper(mvad_tau=0.5, crd_max_new=0.2)
    assert cfg.mvad == MVADConfig(enabled=True, tau=0.5, center="origin")  # the preset's group, one field changed
    assert cfg.crd.max_new == 0.2 and cfg.crd.enabled and cfg.crd.max_miss is None
    with pytest.warns(DeprecationWarning, match="read MVGSConfig.crd.max_new"):
        assert cfg.crd_max_new == 0.2
    with pytest.warns(DeprecationWarning, match=r"MVADConfig\(enabled=True\)"):
        on = dataclasses.replace(MVGSConfig.default(), mvad=True)
    assert on.mvad == MVADConfig(enabled=True)
    assert bool(on.mvad) and not bool(on.crd)  # `if config.mvad:` keeps its old meaning


def test_the_new_spelling_does_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cfg = dataclasses.replace(MVGSConfig.multiview(), crd=dataclasses.replace(MVGSConfig.multiview().crd, enabled=False))
        MVGSConfig.from_dict(cfg.to_dict())
    assert not cfg.crd.enabled and cfg.mvad.enabled


@pytest.mark.parametrize("make, pattern", [
    (lambda: MVADConfig(tau=float("nan")), "mvad.tau must be a finite discrepancy > 0"),
    (lambda: MVADConfig(tau=0.0), "mvad.tau must be a finite discrepancy > 0"),
    (lambda: MVADConfig(rule="all"), "mvad.rule must be 'any' or a fraction"),
    (lambda: MVADConfig(rule=1.5), "mvad.rule must be 'any' or a fraction"),
    (lambda: MVADConfig(center="camera"), "mvad.center must be one of"),
    (lambda: CRDConfig(window=(0, 3)), "crd.window must be"),
    (lambda: CRDConfig(window=(True, 3)), "crd.window must be"),
    (lambda: CRDConfig(max_new=0.0), "crd.max_new must be None or a finite fraction > 0"),
    (lambda: CRDConfig(min_angle_deg=90.0), "crd.min_angle_deg must be a finite angle in \\[0, 90\\)"),
    (lambda: MVGSConfig(mvad="yes"), "mvad must be a MVADConfig"),
    (lambda: MVGSConfig(max_views_rule="cap"), "max_views_rule"),
])
def test_bad_group_values_name_the_field(make, pattern):
    with pytest.raises((ValueError, TypeError), match=pattern):
        make()


def _float_fields(cls):
    """Names of the fields whose annotation admits a float (scalar or tuple of floats)."""
    return [f.name for f in dataclasses.fields(cls) if "float" in str(f.type)]


@pytest.mark.parametrize("cls, group", [(MVADConfig, "mvad"), (CRDConfig, "crd"), (MVGSConfig, None)])
def test_every_float_field_of_every_config_refuses_nan_and_infinity(cls, group):
    """Walks the dataclass fields, so a float field added later is covered without a new test."""
    names = _float_fields(cls)
    assert names, cls
    base = cls()
    types = {f.name: str(f.type) for f in dataclasses.fields(cls)}
    for name in names:
        default = getattr(base, name)
        for bad in (float("nan"), float("inf"), float("-inf")):
            if isinstance(default, tuple):
                value = tuple(bad for _ in default)
            elif "Tuple[float, float, float]" in types[name]:  # e.g. background: "auto" or (r, g, b)
                value = (bad, bad, bad)
            else:
                value = bad
            field = name if group is None else f"{group}.{name}"
            with pytest.raises(ValueError, match=rf"\b{field.split('.')[-1]}\b"):
                if group is None:
                    dataclasses.replace(base, **{name: value})
                else:  # nested: through MVGSConfig, as a user builds it
                    MVGSConfig(**{group: dataclasses.replace(base, **{name: value})})


@pytest.mark.parametrize("flat", ["mvad_rotation_weight", "crd_min_angle_deg", "crd_max_miss", "mvad_tau"])
def test_the_flat_aliases_refuse_nan_too(flat):
    with pytest.warns(DeprecationWarning), pytest.raises(ValueError, match=flat.split("_", 1)[1]):
        MVGSConfig(**{flat: float("nan")})
