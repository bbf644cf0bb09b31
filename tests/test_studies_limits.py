"""Studies within their means (audit of /tmp/audit-studies): the number of joints varied only by
whole numbers that are what the row stores, a large study submitted a window at a time and stopped
at once, and local workers capped at the CPUs the process may use."""

from __future__ import annotations

import re

import pytest

from server.studies.run import apply_values, config_for, run_one
from server.studies.spec import StudyError, expand, study_from

# --- the number of joints -------------------------------------------------------------------------

NJOINTS_REFUSED = [
    # audit: the factor 0.9-1.1 was rounded to 1 joint and every row was a 1-joint neck
    ("geometry.n_joints=10%", "a relative spread"),
    ("geometry.n_joints=U(2,4)", "a uniform draw"),
    ("geometry.n_joints=N(3,0.5)", "a normal draw"),
    # audit: 2.5 was simulated as 2 joints (round half to even) and stored as x = 2.5
    ("geometry.n_joints=2:4:5", "2.5, 3.5 are not whole numbers"),
    ("geometry.n_joints=0:2:3", "1 to 12 joints"),
    ("geometry.n_joints=2:13:12", "1 to 12 joints"),
]


@pytest.mark.parametrize(("vary", "says"), NJOINTS_REFUSED)
def test_the_number_of_joints_is_varied_by_a_grid_of_whole_numbers_only(vary, says) -> None:
    study = study_from("design", samples=2, vary=(vary,), design_configurations=10)
    with pytest.raises(StudyError, match=re.escape(says)) as err:
        config_for(study, "v")
    assert "geometry.n_joints" in str(err.value) and "2:5:4" in str(err.value)  # what to write instead


def test_a_row_stores_the_number_of_joints_it_simulated() -> None:
    study = study_from("design", vary=("geometry.n_joints=2:3:2",), design_configurations=10)
    cfg = config_for(study, "v")
    rows = [run_one(cfg, r) for r in expand(study)]
    assert [(r["x:geometry.n_joints"], r["n_joints"], r["outcome"]) for r in rows] == [(2.0, 2.0, "finished"),
                                                                                      (3.0, 3.0, "finished")]
    with pytest.raises(StudyError, match=r"2\.5 is not a whole number"):  # never rounded behind the row's back
        apply_values(cfg, {"geometry.n_joints": 2.5})
