"""Fitting: per scan and per position (two faces together), batch, joint across scans,
streamed, Dask; north alignment; fit.json and the residual tables."""

from ._align import Alignment, north_alignment
from ._distributed import fit_dask
from ._fit import fit_campaign, fit_scan
from ._joint import JointFit, fit_joint, write_joint_fit
from ._records import fit_json, read_residuals, write_fit
from ._results import CampaignFit, ScanFit
from ._stream import stream_fit_campaign, stream_fit_scan

__all__ = [
    "Alignment",
    "CampaignFit",
    "fit_campaign",
    "fit_dask",
    "fit_joint",
    "fit_json",
    "fit_scan",
    "JointFit",
    "north_alignment",
    "read_residuals",
    "ScanFit",
    "stream_fit_campaign",
    "stream_fit_scan",
    "write_fit",
    "write_joint_fit",
]
