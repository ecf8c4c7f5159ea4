"""Reading Dagster's step events for the user: one line per failure."""

from __future__ import annotations

import os
import sys


def step_failure_reason(event) -> str:
    """One line: the user's ``Failure`` description, else the innermost error under Dagster's
    wrappers (e.g. ``OSError: ...`` raised while storing an output)."""
    data = event.step_failure_data
    if data.user_failure_data and data.user_failure_data.description:
        text = data.user_failure_data.description
    else:
        err = data.error
        while err is not None and err.cls_name and err.cls_name.startswith("Dagster") and err.cause:
            err = err.cause
        text = err.message if err is not None else "failed"
        if err is not None and os.environ.get("FORESTMAP_DEBUG"):
            print("".join(err.stack), file=sys.stderr)
    return (text or "failed").strip().splitlines()[0]
