"""Health of a running API: liveness and readiness for load balancers (routes, public), and the Prometheus
exposition for monitoring (metrics, admin keys only)."""
