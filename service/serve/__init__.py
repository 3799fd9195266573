"""Running the service: the ``complementme`` command line and its logging.

Owns the ``complementme`` command line (``cli``: its root app and entry point, the serve,
suggest and batch commands, and the ``complementme.commands`` group through which training adds
its own), the log format and library log levels (``logs``), and the re-export of the Python
client the commands use (``client``). ``complementme serve`` runs one server process; several on
one machine run behind a proxy (docker/haproxy/haproxy.cfg). Besides ``service.api`` it is the
only package that may name the HTTP app, because it starts it.
"""
