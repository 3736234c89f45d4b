# SPDX-License-Identifier: MIT
"""Command-line tools: offline fit and the demo."""
