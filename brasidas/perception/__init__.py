"""What the robot sees (issue 30): lidar scans, obstacles, collision prevention."""
