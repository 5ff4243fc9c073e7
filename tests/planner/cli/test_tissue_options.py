"""``--tissue-modulus``, ``--organ-modulus`` and ``--modulus-band`` on ``plan`` and ``demo``: the plan's settings.

The band they give is tested with the report (``tests/planner/report/test_report_tissue.py``).
"""

from __future__ import annotations

import pytest

from reachplan.planner.case.config import PlanConfig, PlanModels
from reachplan.planner.cli import build_parser
from reachplan.planner.cli.tissue import tissue_options
from reachplan.planner.steering.tissue_band import DEFAULT_SOURCE, ModulusBand


@pytest.mark.parametrize("command", ["plan", "demo"])
def test_tissue_options_set_the_plan_config_in_pascal(command: str) -> None:
    base = ["plan", "--rtstruct", "RS.dcm", "--targets", "T", "--out", "o"] if command == "plan" else \
        ["demo", "--out", "o"]
    args = build_parser().parse_args([*base, "--tissue-modulus", "0.4", "--organ-modulus", "Uterus=0.6",
                                      "--organ-modulus", "Cervix=1.5", "--modulus-band", "2"])
    config = PlanConfig(**tissue_options(args))
    assert config.tissue_modulus_pa == pytest.approx(0.4e6)
    assert config.tissue_moduli_pa == (("Uterus", pytest.approx(0.6e6)), ("Cervix", pytest.approx(1.5e6)))
    assert config.modulus_band.factor == 2.0 and config.modulus_band.source == "given: --modulus-band 2"
    models = PlanModels.for_config(config)  # every model in the plan's tissue
    assert [models.screening.tissue_modulus_pa, models.reference.tissue_modulus_pa,
            models.robustness.tissue_modulus_pa] == pytest.approx([0.4e6] * 3)
    default = PlanConfig(**tissue_options(build_parser().parse_args(base)))
    assert default.tissue_modulus_pa == 0.19e6 and default.modulus_band == ModulusBand()
    assert default.modulus_band.source == DEFAULT_SOURCE


@pytest.mark.parametrize(("option", "message"), [
    (["--tissue-modulus", "0.05"], "outside [0.1, 10] MPa"),
    (["--tissue-modulus", "nan"], "not a finite number"),
    (["--organ-modulus", "Uterus"], "ORGAN=MPA"),
    (["--organ-modulus", "Uterus=20"], "outside [0.1, 10] MPa"),
    (["--modulus-band", "0.5"], "factor in [1, 10]"),
])
def test_bad_tissue_options_are_usage_errors(option: list[str], message: str,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["demo", "--out", "o", *option])
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_a_modulus_below_the_screening_range_is_refused_by_the_config() -> None:
    with pytest.raises(ValueError, match=r"at least 0\.1 MPa"):
        PlanConfig(tissue_modulus_pa=5e4)
    with pytest.raises(ValueError, match="Uterus"):
        PlanConfig(tissue_moduli_pa=(("Uterus", 1e4),))
