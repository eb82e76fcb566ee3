"""The fleet runtime, in the API's process or in one of its own (``local``, ``host``, ``client``,
``replicas``; what crosses between them: ``wire``)."""
