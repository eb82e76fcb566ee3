"""Simulated robots: task suite, action space, teleoperation command, scripted experts."""
