"""bimacppo_common: what the bimacppo packages share. It imports none of them and no ROS, so
every package may depend on it without a cycle (the configuration mechanism: ``config``)."""

__version__ = "0.1.0"
