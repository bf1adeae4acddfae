"""One adapter per message encoding (Foxglove protobuf/JSON, ROS 1, ROS 2) and the explicit
table of supported schemas."""
