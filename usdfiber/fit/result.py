"""Settings and results of a fit (:class:`FitSettings`, :class:`FitResult`)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from usdfiber.fit.chiang import ChiangParams
from usdfiber.fit.khungurn import KhungurnParams

__all__ = ["FitResult", "FitSettings", "PARAMS_TYPES"]

#: The parameter class of each model.
PARAMS_TYPES: dict[str, type] = {"chiang": ChiangParams, "khungurn": KhungurnParams}


@dataclass(frozen=True)
class FitSettings:
    """What changes a fit's result (all of it is part of the fit's cache key).

    ``floor``: the objective's floor ``eps`` as a fraction of the target's mean
    (:mod:`usdfiber.fit.objective`); ``offsets``: Gauss nodes of the average over the offset
    ``h`` (Chiang); ``theta_nodes``: Gauss nodes per theta_o bin; ``tints``: fit Chiang's
    per-lobe tints (MaterialX has them, Mitsuba's ``hair`` does not); ``energy_weight``: the
    weight of the albedo terms of the objective; ``max_evaluations``: per least-squares solve.
    """

    floor: float = 0.02
    energy_weight: float = 1.0
    offsets: int = 32
    theta_nodes: int = 3
    tints: bool = False
    max_evaluations: int = 200

    def __post_init__(self) -> None:
        if not (self.energy_weight >= 0.0):
            raise ValueError(f"energy_weight must be >= 0, got {self.energy_weight}")
        if not (0.0 < self.floor < 1.0):
            raise ValueError(f"floor must be in (0, 1), got {self.floor}")
        if self.offsets < 8 or self.theta_nodes < 1 or self.max_evaluations < 10:
            raise ValueError("offsets >= 8, theta_nodes >= 1 and max_evaluations >= 10 are needed")

    def key_inputs(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class FitResult:
    """A fitted model and its error against the table it was fitted to.

    ``params``: :class:`~usdfiber.fit.chiang.ChiangParams` or
    :class:`~usdfiber.fit.khungurn.KhungurnParams`, with one value per colour channel of
    ``sigma_a``. ``error``: per channel lists ``rel_l2`` (relative L2 of the scattering over
    the sphere), ``rms_log`` (the objective), ``albedo_table`` and ``albedo_model`` (mean
    directional albedo, weights cos theta_i). ``sigma_a``: the effective absorption the
    tables were recoloured for (1/um at the baked size). ``tables``: the tables' identities.
    """

    model: str
    params: Any
    error: dict[str, list[float]]
    key: str
    tables: list[str]
    sigma_a: list[float]
    settings: FitSettings
    seconds: float
    evaluations: int
    cached: bool = field(default=False, compare=False)

    def to_json(self) -> dict[str, Any]:
        return {"model": self.model, "params": self.params.to_json(), "error": self.error, "key": self.key,
                "tables": list(self.tables), "sigma_a": list(self.sigma_a),
                "settings": self.settings.key_inputs(), "seconds": self.seconds,
                "evaluations": self.evaluations}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "FitResult":
        model = str(d["model"])
        if model not in PARAMS_TYPES:
            raise ValueError(f"unknown model {model!r}")
        return cls(model=model, params=PARAMS_TYPES[model].from_json(d["params"]),
                   error={k: [float(x) for x in v] for k, v in d["error"].items()}, key=str(d["key"]),
                   tables=[str(x) for x in d["tables"]], sigma_a=[float(x) for x in d["sigma_a"]],
                   settings=FitSettings(**d["settings"]), seconds=float(d["seconds"]),
                   evaluations=int(d["evaluations"]))
