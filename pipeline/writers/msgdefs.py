"""The ros2msg schema texts of the message types the MCAP writer writes, as rosbags generates
them (``get_typestore(Stores.ROS2_HUMBLE).generate_msgdef(type, ros_version=2)[0]``).

Kept here because building rosbags' typestore costs about 0.1 s of every ``imupipe convert`` and
``run`` (206 dataclasses), a third of a small log's whole command; ``tests/test_msgdefs.py``
checks each text equals rosbags' output, so a new rosbags that changes one fails the test. The
definitions are those of ROS 2 Humble's ``sensor_msgs`` and ``std_msgs`` (ros2/common_interfaces,
Apache-2.0).
"""

MSGDEFS: dict[str, str] = {
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\n"
        "float64[9] linear_acceleration_covariance\n"
        "================================================================================\n"
        "MSG: std_msgs/Header\n"
        "builtin_interfaces/Time stamp\n"
        "string frame_id\n"
        "================================================================================\n"
        "MSG: builtin_interfaces/Time\n"
        "int32 sec\n"
        "uint32 nanosec\n"
        "================================================================================\n"
        "MSG: geometry_msgs/Quaternion\n"
        "float64 x\n"
        "float64 y\n"
        "float64 z\n"
        "float64 w\n"
        "================================================================================\n"
        "MSG: geometry_msgs/Vector3\n"
        "float64 x\n"
        "float64 y\n"
        "float64 z\n"
    ),
    "sensor_msgs/msg/MagneticField": (
        "std_msgs/Header header\n"
        "geometry_msgs/Vector3 magnetic_field\n"
        "float64[9] magnetic_field_covariance\n"
        "================================================================================\n"
        "MSG: std_msgs/Header\n"
        "builtin_interfaces/Time stamp\n"
        "string frame_id\n"
        "================================================================================\n"
        "MSG: builtin_interfaces/Time\n"
        "int32 sec\n"
        "uint32 nanosec\n"
        "================================================================================\n"
        "MSG: geometry_msgs/Vector3\n"
        "float64 x\n"
        "float64 y\n"
        "float64 z\n"
    ),
    "sensor_msgs/msg/Temperature": (
        "std_msgs/Header header\n"
        "float64 temperature\n"
        "float64 variance\n"
        "================================================================================\n"
        "MSG: std_msgs/Header\n"
        "builtin_interfaces/Time stamp\n"
        "string frame_id\n"
        "================================================================================\n"
        "MSG: builtin_interfaces/Time\n"
        "int32 sec\n"
        "uint32 nanosec\n"
    ),
}
