"""ROS 2 nodes of magcal_ros: live correction and the calibration service.

These modules import rclpy; the math lives in the ROS-free core (:mod:`magcal_ros`).
"""
