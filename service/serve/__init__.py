"""Running the service: the ``complementme`` command line, logging and worker processes.

Owns the ``complementme`` command line (``cli``: its root app and entry point, the serve,
suggest and batch commands, and the ``complementme.commands`` group through which training adds
its own), the log format and library log levels (``logs``), the supervisor that runs several
server processes on one port (``workers``) with the balancer that deals connections out to them
(``balancer``), and the re-export of the Python client the commands use (``client``). Besides
``service.api`` it is the only package that may name the HTTP app, because it starts it.
"""
