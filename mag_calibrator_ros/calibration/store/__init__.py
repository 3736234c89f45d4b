# SPDX-License-Identifier: MIT
"""store"""
