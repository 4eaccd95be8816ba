"""quatrack.recognition — not yet implemented (see the open issues)."""
