"""Place-recognition methods VBRL is compared with: :mod:`.scan_context`."""
