"""quatrack.viewsets — not yet implemented (see the open issues)."""
