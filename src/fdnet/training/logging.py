"""Training logs: a CSV of losses per logged step, and TensorBoard events when installed."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from fdnet.io import atomic_write_text

LOG_FILE = "log.csv"


class TrainingLog:
    """Appends rows to ``RUN_DIR/log.csv`` (one flushed line per write: a crash loses at most the
    line being written) and mirrors numbers to TensorBoard if ``torch.utils.tensorboard`` works."""

    def __init__(self, run_dir: str | Path, columns: list[str], tensorboard: bool = True) -> None:
        self.path = Path(run_dir) / LOG_FILE
        self.columns = list(columns)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.writer = None
        if tensorboard:
            try:  # optional: needs the tensorboard package
                from torch.utils.tensorboard import SummaryWriter

                self.writer = SummaryWriter(str(Path(run_dir) / "tensorboard"))
            except Exception:  # noqa: BLE001 - absent or broken tensorboard just means no events
                self.writer = None

    def truncate_after(self, step: int) -> None:
        """Drop rows logged after ``step`` (written after the checkpoint a resume starts from)."""
        if not self.path.exists():
            return
        with self.path.open(newline="") as handle:
            # A kill -9 mid-write can leave a partial last line; it is dropped with the rest.
            rows = list(csv.DictReader(handle))
        kept = [r for r in rows if r.get("step", "").isdigit() and int(r["step"]) <= step]
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=self.columns)
        writer.writeheader()
        writer.writerows(kept)
        atomic_write_text(self.path, buffer.getvalue())

    def write(self, row: dict) -> None:
        new = not self.path.exists()
        try:
            with self.path.open("a", newline="") as handle:
                writer = csv.DictWriter(handle, fieldnames=self.columns)
                if new:
                    writer.writeheader()
                writer.writerow(
                    {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items() if k in self.columns}
                )
        except OSError as exc:  # a full disk: a write() error names no file, so name it here
            if exc.filename is not None:
                raise
            raise OSError(exc.errno, exc.strerror, str(self.path)) from exc
        if self.writer is not None:
            for key, value in row.items():
                if isinstance(value, float):
                    self.writer.add_scalar(key, value, int(row["step"]))

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
