"""The columns of the tables the analysis passes around: ``runs`` makes them, ``stats`` reads them."""

from __future__ import annotations

__all__ = ["CURVE_COLUMNS", "RECORD_COLUMNS", "RETURN_COL", "STEP_COL"]

RETURN_COL = "average_return"
STEP_COL = "step"

#: Columns of the per-run table (``records``) and of ``ablation.csv``.
RECORD_COLUMNS = ["env", "variant", "seed", "final_return", "auc"]
#: Columns of the long learning-curve table (``curves``).
CURVE_COLUMNS = ["env", "variant", "seed", "step", "average_return"]
