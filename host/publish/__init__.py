"""Publishing: the live 3D view (`live`), Zenoh (`zenoh_pub`), ROS 2 over Zenoh (`ros2`), and the
multi-sheet robot configuration (`robot`)."""
