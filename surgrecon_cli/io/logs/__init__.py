"""Reading logs: MCAP, ROS bags, the encodings of their messages, images and video, topic
roles; the simulator's ground truth and register-pair's input files."""
