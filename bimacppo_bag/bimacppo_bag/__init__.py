"""bimacppo_bag: MCAP record and replay of the graph.

``recorder`` (``mcap_recorder``) writes what the graph publishes, rosbag2-compatible;
``player`` (``mcap_player``) republishes a recording so it can stand in for the world;
``mcap_io`` reads and writes MCAP without rclpy; ``bag_frames`` turns a recording into the
frames ``bimacppo-sim render-bag`` draws. It knows the contract, no role.
"""
