"""The web dashboard: the bridge from the fleet to browsers (hub) and the page's static files (static/)."""
