"""The fleet service: the control loop over the robot workers (``fleet``), the assistance queue, takeover
recording, the policy registry and fine-tuning jobs, and the REST/WebSocket API (``api/``, ``app``).

The app as it runs, with the operator console mounted, is assembled one level up in ``service.app``."""
