"""The hitl command line."""
