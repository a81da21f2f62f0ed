"""The one exception the reconstruction stages raise for a flight they cannot reconstruct."""

from __future__ import annotations


class ReconstructionError(RuntimeError):
    """A flight could not be reconstructed (too few images, no features, too few registered).

    Attributes:
        record: a flat JSON-able record of the failure (``status``, ``stage``, ``n_images``,
            ``registered_fraction``, ...) for ``metrics.json``.
    """

    def __init__(self, message: str, record: dict | None = None) -> None:
        super().__init__(message)
        self.record = {"status": "failed", "error": message, **(record or {})}
