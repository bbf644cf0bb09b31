"""An identification campaign's estimates as a parameter set of the console (``POST
/api/campaigns/{id}/parameter-set``): what ``xneck identify CAMPAIGN.mcap --out DIR`` writes, stored
where campaigns can use it and ``PUT /api/params/active`` can choose it.

The base is the set the campaign ran with (the archive's ``parameters_toml``), the analysis the one
its record asked for (estimator, creep time), so the set saved is the one its tables showed. The
identification runs again on the archive (a few seconds): the record keeps the tables, not the
estimates. Never overwrites a set. On the twin, the robot truth's robot stays the prototype's
whatever set is active (twin/sim/truth.py, ``robot_params``), so a control campaign with the saved
set against one with the base set compares what the controller believes, not two robots.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from server.paramsets import BUILTIN, ParameterStore, check_name
from server.records import CampaignRecord


class NotIdentified(ValueError):
    """The campaign has no identification to save (another kind, or its analysis failed)."""


def save_identified_set(mcap: Path, rec: CampaignRecord, store: ParameterStore, name: str) -> dict[str, Any]:
    """Identify ``mcap`` again as its record asked and store the set as ``name``. Raises
    :class:`NotIdentified`, :class:`twin.model.params.ParameterError` (a bad name),
    :class:`FileExistsError` (the name is taken), or
    :class:`twin.identification.pipeline.IdentificationError` (the archive does not identify)."""
    from bridge.archive import ArchiveError, read_campaign
    from controller.trajectory import recorded_excitation
    from twin.identification.pipeline import IdentificationError, identified_toml, structure_overrides
    from twin.identification.record import identify_record
    from twin.model.params import ParameterError, params_from_dict

    if rec.kind != "identification":
        raise NotIdentified(f"campaign {rec.id} is a {rec.kind} campaign: only an identification campaign has estimates")
    if rec.identification_status != "identified":
        raise NotIdentified(f"campaign {rec.id} has no identification to save ({rec.status}"
                            + (f": {rec.identification_status}" if rec.identification_status else "") + ")")
    check_name(name)
    if name == BUILTIN or name in store.names():
        raise FileExistsError(f"a parameter set {name!r} exists: choose another name")
    try:
        info = read_campaign(mcap).info
        base = params_from_dict(tomllib.loads(info["parameters_toml"]), f"campaign {rec.id}")
    except ArchiveError as exc:
        raise IdentificationError(f"cannot read campaign {rec.id}: {exc}") from None
    except (KeyError, tomllib.TOMLDecodeError, ParameterError) as exc:
        raise IdentificationError(f"campaign {rec.id} does not record a usable parameter set ({exc})") from None
    ident = identify_record(mcap, base, excitation=recorded_excitation, with_validation=False,
                            estimator=rec.estimator or "auto", creep_time_s=rec.creep_time_s)
    store.save(name, identified_toml(ident.params, ident.provenance), replace=False)
    return {"name": name, "campaign": rec.id, "base_parameter_set": base.name,
            "used": ident.report.used,
            "kept_base": {k: why for k, (_, _, why) in ident.report.kept_base.items()},
            "structure_set": structure_overrides(ident.provenance.parameters)}
