"""The Pusher competency study: the paper's table and figure, and every forecast checked
against real rollouts of the same agent (``main.py`` runs it)."""
