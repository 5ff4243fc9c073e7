"""Fixtures of the rod-model tests."""

from __future__ import annotations

from dataclasses import replace

import pytest

from reachplan.rod_model.design import RodDesign, preset


@pytest.fixture(scope="session")
def uniform_design() -> RodDesign:
    """15 ga design whose joint section has the tube's stiffness and moment arm: one uniform rod."""
    d = preset("15ga-20j-tip")
    st = d.stylet
    st = replace(st, joint_bending_stiffness_nm2=st.tube_bending_stiffness_nm2 / st.calibration.joint_stiffness_scale,
                 joint_torsion_stiffness_nm2=st.tube_torsion_stiffness_nm2, disk_arm_mm=st.tube_arm_mm)
    return replace(d, name="uniform", stylet=st)


@pytest.fixture
def builtin_models(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make the built-in rod models reachable through the plugin registry even before their entry points are
    installed (the registry itself is tested in tests/plugins)."""
    from reachplan.plugins import registry
    from reachplan.rod_model.beam import PLANAR_BEAM
    from reachplan.rod_model.cosserat import COSSERAT_ROD, TWO_TUBE_COSSERAT
    from reachplan.rod_model.kinematic import CONSTANT_CURVATURE

    builtins = {m.name: m for m in (CONSTANT_CURVATURE, PLANAR_BEAM, COSSERAT_ROD, TWO_TUBE_COSSERAT)}
    if set(builtins) <= set(registry.names("rod_models")):
        return
    real_get = registry.get

    def get(kind: str, name: str) -> object:
        if kind == "rod_models" and name in builtins:
            return builtins[name]
        return real_get(kind, name)

    monkeypatch.setattr(registry, "get", get)
