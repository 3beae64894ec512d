"""Observability: Prometheus metrics (metrics, multiprocess, collectors, queue_depths), structured logs (logs),
request ids (request_id) and the HTTP middleware that ties them to each request (http).

Kept free of imports here: the metrics directory must be set up before prometheus_client is first imported
(see multiprocess), and importing this package must not do that.
"""
