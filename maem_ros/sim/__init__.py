"""Synthetic court scenes: rigs, player motion, fixed-topology body mesh, detection noise, images.

Entry point: ``Scene(SceneConfig(rig="sportcenter6", frames=90, difficulty="medium", seed=0))``.
"""

__all__ = ["Scene", "SceneConfig"]


def __getattr__(name: str):
    # lazy, so `from maem_ros.sim.rigs import ...` does not load the whole simulator
    if name in __all__:
        from . import scene

        return getattr(scene, name)
    raise AttributeError(f"module 'maem_ros.sim' has no attribute {name!r}")
