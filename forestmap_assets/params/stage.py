"""The base of every parameter section: frozen, no unknown keys, hashed for code versions."""

from __future__ import annotations

import hashlib
import json

from pydantic import BaseModel, ConfigDict


class _Stage(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    def digest(self) -> str:
        """Short stable hash of this section's values (for Dagster code versions)."""
        text = json.dumps(self.model_dump(mode="json"), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]
