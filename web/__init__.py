"""The operator console in the browser: a viser server behind the service's authenticated proxy
(``pages``, ``proxy``), one operator panel and scene per browser, mounted on the service as an
extension (``extension``)."""
