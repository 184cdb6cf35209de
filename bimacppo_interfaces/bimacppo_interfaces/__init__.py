"""bimacppo_interfaces: the ROS interface contract of the stack (``contract``).

docs/interfaces.md is its prose; every node, tool and test converts through ``contract``, so a
name, profile or convention is decided once. It depends only on standard message packages and
bimacppo_common, never on a node of any role.
"""
