# SPDX-License-Identifier: MIT
"""sim"""
