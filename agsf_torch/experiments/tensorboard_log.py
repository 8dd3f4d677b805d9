"""An experiment's TensorBoard events: scalars per step and weight histograms."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_tensorboard"]


def write_tensorboard(out: Path, data: dict[str, np.ndarray], summary: dict[str, Any]) -> None:
    """Write the events of one experiment under ``out/tensorboard`` from its data and summary."""
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(out / "tensorboard"))
    frames = data["star_frame"]
    for name, f in summary["filters"].items():
        rms = f["rms_deg"]
        nees = f["nees_mean"]
        nis = data[f"{name}/nis"]
        weights = data[f"{name}/weights"]
        entropy = data[f"{name}/weight_entropy"].mean(0)
        for k in range(len(rms)):
            writer.add_scalar(f"{name}/rms_deg", rms[k], k)
            writer.add_scalar(f"{name}/nees", nees[k], k)
            writer.add_scalar(f"{name}/weight_entropy", entropy[k], k)
            if frames[k]:
                writer.add_scalar(f"{name}/nis", float(np.nanmean(nis[:, k])), k)
            for i in range(weights.shape[-1]):
                writer.add_scalar(f"{name}/weight_{i}_run0", weights[0, k, i], k)
            if "fpke_error_before_mean" in f:
                writer.add_scalar(f"{name}/fpke_error_before", f["fpke_error_before_mean"][k], k)
                writer.add_scalar(f"{name}/fpke_error_after", f["fpke_error_after_mean"][k], k)
            if weights.shape[-1] > 1 and (frames[k] or k % 10 == 0):
                writer.add_histogram(f"{name}/weights", weights[:, k].reshape(-1), k)
    writer.close()


