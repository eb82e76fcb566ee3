"""The service as it runs: the fleet service (``server/``) and the operator console (``web/``) assembled
into one app, above both packages so that neither imports the other upwards."""
