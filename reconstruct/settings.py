"""The reconstruction stage's settings in a cell: the ``reconstruct`` group detached from the run
config, with its typed blocks (SfM, dense, the proxy flight's dense) checked once at the top of the
cell (``pipeline.settings.cell_settings``) and handed down."""

from __future__ import annotations

from dataclasses import dataclass

from omegaconf import DictConfig

from reconstruct.dense_settings import DenseSettings
from reconstruct.sfm_settings import SfmSettings
from scene.config import StageSettings, detached


@dataclass(frozen=True)
class ReconstructSettings(StageSettings):
    """The ``reconstruct`` group of a cell (``reconstruct_flight`` and ``oracle_flight`` read it).

    Attributes:
        node: the group, resolved (the stage's cache keys hash it).
        sfm: its ``sfm`` block, typed.
        dense: its ``dense`` block, typed.
        proxy_dense: the dense settings the exploratory flight runs with (``proxy.dense`` over
            ``dense``), typed.
    """

    sfm: SfmSettings
    dense: DenseSettings
    proxy_dense: DenseSettings

    @classmethod
    def build(cls, node: DictConfig, proxy_dense: dict) -> ReconstructSettings:
        """Check and type ``node`` (a ``ValueError`` names the bad setting)."""
        return cls(
            detached(node),
            SfmSettings.from_config(node.sfm),
            DenseSettings.from_config(node.dense),
            DenseSettings.from_config(proxy_dense, "reconstruct.proxy.dense"),
        )

    @property
    def oracle_beside(self) -> bool:
        """Whether the cell also runs the oracle beside its reconstruction."""
        return bool(self.node.get("oracle_beside", False))
