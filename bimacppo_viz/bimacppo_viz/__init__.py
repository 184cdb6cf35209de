"""bimacppo_viz: viewing tools for the bimacppo graph. ``scene`` turns graph states into Foxglove
messages (no ROS); ``ros.live_view`` serves them live on a Foxglove WebSocket server; the shipped
layout (``layouts/bimacppo_live.json``, :func:`layout_path`) opens the 3D scene and the plots."""
from importlib import resources

__version__ = "0.1.0"

LAYOUT = "bimacppo_live.json"


def layout_path() -> str:
    """Where the shipped Foxglove layout lies in this installation."""
    return str(resources.files(__name__).joinpath("layouts", LAYOUT))
