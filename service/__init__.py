"""quatrack.service — not yet implemented (see the open issues)."""
