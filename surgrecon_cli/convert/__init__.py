"""`surgrecon convert`: stereo / multi-camera image folders and videos plus a calibration file
-> a standard ROS 2 (CDR) MCAP log and a config that runs it.

calibration_files  calibration files (OpenCV FileStorage, ROS camera_info, JSON, rectified
                   text) -> plain dicts
calibration        those dicts -> a `Rig` (intrinsics + camera-to-rig poses in metres)
sources            image folders and videos -> per-frame encoded images (bytes kept)
stamps             frame stamps (--fps / a stamps file) and TUM pose files
write              the messages (images, CameraInfo, /tf, /tf_static) and the config text
"""
