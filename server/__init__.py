"""Fleet service: FastAPI app, policy workers, assistance queue (arrives with the fleet issue)."""
