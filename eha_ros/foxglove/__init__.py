"""The live view: the graph in Foxglove over its WebSocket protocol (:mod:`.core`, ROS-free;
the node is :mod:`eha_ros.nodes.foxglove_bridge`)."""
