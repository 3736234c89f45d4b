# SPDX-License-Identifier: MIT
"""fit"""
