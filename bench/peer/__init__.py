"""The peer baseline: the same trained model served the way a user would write it without this
project (torch eager in a plain FastAPI handler; see ``bench.peer.app``)."""
