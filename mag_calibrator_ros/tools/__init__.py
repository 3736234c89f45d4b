"""Command-line tools: offline fit and the demo."""
