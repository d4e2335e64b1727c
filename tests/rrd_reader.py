"""Read a Rerun recording back for the tests (rerun 0.41: `RrdReader`, one Arrow batch per chunk)."""

from __future__ import annotations

from pathlib import Path

from rerun.chunk import RrdReader


def read_rrd(path: Path) -> dict[str, dict[str, dict]]:
    """entity -> component -> {step: value} (key None for static data)."""
    out: dict[str, dict[str, dict]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        steps = batch.column("step").to_pylist() if "step" in batch.schema.names else [None] * batch.num_rows
        entity = out.setdefault(chunk.entity_path, {})
        for field, column in zip(batch.schema, batch.columns):
            if (field.metadata or {}).get(b"rerun:kind") == b"data":
                entity.setdefault(field.name, {}).update(zip(steps, column.to_pylist()))
    return out
