"""RQ job functions (`workers.jobs`) and the worker process entry point (`workers.main`).

Workers import `service`; the service never imports this package: it enqueues jobs by dotted path
(service.queue), so the API process never loads the geometry just to hand work over.
"""
