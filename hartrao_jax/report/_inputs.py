"""Collecting what a report shows: ``fit.json``, ``surface.json`` and ``preprocess.json`` (in
the directory or its sub-directories), the campaign and, for simulated ones, its truth."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..campaign._campaign import CampaignError, load_campaign
from ..campaign._safeio import verify_result_dir
from ..surface._disturbed import detect_disturbed_residuals
from ..surface._surface import (
    SurfaceResult,
    read_surface,
    surface_from_fit_dir,
)

log = logging.getLogger("hartrao_jax")


_MODEL_ORDER = {"simplified": 0, "extended": 1}


@dataclass
class ReportInputs:
    root: Path
    fits: list[tuple[str, Path, dict]] = field(default_factory=list)
    surfaces: list[tuple[str, SurfaceResult]] = field(default_factory=list)
    preprocess: list[tuple[str, dict]] = field(default_factory=list)
    disturbed: list = field(default_factory=list)  # DisturbedReport objects or dicts
    campaign: Any = None
    truth: dict | None = None


def _label(root: Path, d: Path) -> str:
    rel = d.relative_to(root)
    return str(rel) if str(rel) != "." else "results"


def _find(root: Path, name: str) -> list[Path]:
    out = [root / name] if (root / name).is_file() else []
    for pat in (f"*/{name}", f"*/*/{name}"):
        out += sorted(root.glob(pat))
    return out


def collect(results_dir, campaign=None) -> ReportInputs:
    """Find fits, surfaces, preprocessing and disturbed-scan results under ``results_dir``."""
    root = Path(results_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: results directory not found")
    inp = ReportInputs(root)

    for p in _find(root, "fit.json"):
        # an incomplete or mixed fit directory is refused (one-line CampaignError)
        doc = verify_result_dir(p.parent, "fit.json")
        if str(doc.get("schema", "")).startswith("hartrao-fit/"):
            inp.fits.append((_label(root, p.parent), p.parent, doc))
    inp.fits.sort(key=lambda t: (_MODEL_ORDER.get(Path(t[0]).name, 5), t[0]))
    if campaign is None:
        for _, _, doc in inp.fits:
            c = doc.get("campaign")
            if c and (Path(c) / "campaign.toml").exists():
                try:
                    campaign = load_campaign(c)
                    break
                except Exception as e:  # noqa: BLE001
                    log.warning("campaign %s not readable: %s", c, e)
    inp.campaign = campaign
    if campaign is not None and (Path(campaign.root) / "truth.json").exists():
        try:
            inp.truth = json.loads((Path(campaign.root) / "truth.json").read_text())
        except (OSError, ValueError):
            pass
    for p in _find(root, "surface.json"):
        try:
            verify_result_dir(p.parent, "surface.json")  # refused when incomplete or mixed
            inp.surfaces.append((_label(root, p.parent), read_surface(p.parent)))
        except Exception as e:  # noqa: BLE001
            if isinstance(e, CampaignError):
                raise
            log.warning("%s: not readable (%s), skipped", p, e)
    inp.surfaces.sort(key=lambda t: (_MODEL_ORDER.get(Path(t[0]).name, 5), t[0]))  # as fits
    if not inp.surfaces:
        for label, d, _ in inp.fits:
            if (d / "residuals").is_dir():
                try:
                    inp.surfaces.append((label, surface_from_fit_dir(d, campaign=campaign)))
                except Exception as e:  # noqa: BLE001
                    log.warning("surface products of %s failed: %s", d, e)
    for p in _find(root, "preprocess.json"):
        try:
            inp.preprocess.append((_label(root, p.parent), json.loads(p.read_text())))
        except (OSError, ValueError):
            pass
    main = _main_fit(inp)
    if main is not None and (main[1] / "residuals").is_dir():
        try:
            inp.disturbed = detect_disturbed_residuals(main[1])
        except Exception as e:  # noqa: BLE001
            log.warning("disturbed-scan search failed: %s", e)
    else:
        for _, s in inp.surfaces:
            inp.disturbed += list(s.disturbed)
    if not inp.disturbed:
        for p in _find(root, "disturbed.json"):
            try:
                inp.disturbed += list(json.loads(p.read_text()).get("disturbed", []))
            except (OSError, ValueError):
                pass
    return inp


def _main_fit(inp: ReportInputs):
    return inp.fits[-1] if inp.fits else None

