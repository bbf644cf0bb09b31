"""An identification campaign's estimates as a parameter set of the console (``POST
/api/campaigns/{id}/parameter-set``): what ``xneck identify CAMPAIGN.mcap --out DIR`` writes, stored
where campaigns can use it and ``PUT /api/params/active`` can choose it.

The base is the set the campaign ran with, the analysis the one its record asked for (estimator,
creep time), so the set saved is the one its tables showed. The campaign's own analysis keeps the
set it identified beside the record (:data:`CACHE_NAME` in the campaign's figures folder, written by
:mod:`server.campaigns`), so a save is a copy; without it (a record from before, a damaged file) the
identification runs again on the archive with the archive's ``parameters_toml`` as base (seconds of
CPU). Never overwrites a set. On the twin, the robot truth's robot stays the prototype's
whatever set is active (twin/sim/truth.py, ``robot_params``), so a control campaign with the saved
set against one with the base set compares what the controller believes, not two robots.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bridge import toml_text
from server.paramsets import BUILTIN, ParameterStore, check_name
from server.records import CampaignRecord

if TYPE_CHECKING:
    from twin.identification.record import Identification

#: The identified set a campaign's analysis kept (JSON of :func:`identified_set`), in its figures folder.
CACHE_NAME = "identified-set.json"
#: A kept set without ``warning`` (kept before sets said one) is identified again: its warning is not known.
_CACHE_KEYS = {"toml": str, "base_parameter_set": str, "used": dict, "kept_base": dict, "structure_set": list,
               "warning": str}


class NotIdentified(ValueError):
    """The campaign has no identification to save (another kind, or its analysis failed)."""


def identified_set(ident: Identification, base_name: str) -> dict[str, Any]:
    """What a save stores and answers, from an identification of the campaign on base set
    ``base_name``: the TOML and which values were used, kept (why) and reported as structure;
    ``warning``, why the set is not to be trusted ('' for none: α_IP stamped off, as ``xneck
    identify`` says), also first in the TOML's header."""
    from twin.identification.pipeline import identified_toml, structure_overrides, warned
    from twin.identification.timing import alpha_ip_timing

    provenance = ident.provenance
    if (timing := alpha_ip_timing(ident.data)).warn:
        provenance = warned(provenance, timing.text())
    return {"toml": identified_toml(ident.params, provenance), "warning": provenance.warning,
            "base_parameter_set": base_name,
            "used": ident.report.used, "kept_base": {k: why for k, (_, _, why) in ident.report.kept_base.items()},
            "structure_set": structure_overrides(ident.provenance.parameters)}


def cached_set(folder: Path) -> dict[str, Any] | None:
    """The set the campaign's analysis kept in ``folder``, or None (none kept, unreadable, damaged:
    the save then identifies again)."""
    try:
        doc = json.loads((folder / CACHE_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # damaged, however: identified again (not a 500)
        return None
    if not isinstance(doc, dict) or any(not isinstance(doc.get(k), t) for k, t in _CACHE_KEYS.items()):
        return None
    return doc


def save_identified_set(mcap: Path, rec: CampaignRecord, store: ParameterStore, name: str,
                        cached: dict[str, Any] | None = None) -> dict[str, Any]:
    """Store the set ``mcap``'s analysis identified as ``name``: ``cached`` (:func:`cached_set`) if
    given, else identified again as the record asked. Raises
    :class:`NotIdentified`, :class:`twin.model.params.ParameterError` (a bad name),
    :class:`FileExistsError` (the name is taken), or
    :class:`twin.identification.pipeline.IdentificationError` (the archive does not identify)."""
    from bridge.archive import ArchiveError
    from bridge.archive_read import read_campaign_info
    from controller.trajectory import recorded_excitation
    from twin.identification.pipeline import IdentificationError
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
    if cached is not None:
        try:
            store.validate(cached["toml"], f"{name}.toml")
        except ParameterError:  # damaged in a way its shape does not show: identified again below
            cached = None
    if cached is None:
        try:
            info = read_campaign_info(mcap)
            base = params_from_dict(toml_text.loads(info["parameters_toml"]), f"campaign {rec.id}")
        except ArchiveError as exc:
            raise IdentificationError(f"cannot read campaign {rec.id}: {exc}") from None
        except (KeyError, tomllib.TOMLDecodeError, ParameterError) as exc:
            raise IdentificationError(f"campaign {rec.id} does not record a usable parameter set ({exc})") from None
        ident = identify_record(mcap, base, excitation=recorded_excitation, with_validation=False,
                                estimator=rec.estimator or "auto", creep_time_s=rec.creep_time_s)
        cached = identified_set(ident, base.name)
    store.save(name, cached["toml"], replace=False)
    return {"name": name, "campaign": rec.id, **{k: v for k, v in cached.items() if k != "toml"}}
