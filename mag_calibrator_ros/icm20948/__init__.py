"""Hardware layer: ICM-20948 / AK09916 registers, driver and register-level simulator; no rclpy."""
