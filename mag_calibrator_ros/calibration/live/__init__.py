# SPDX-License-Identifier: MIT
"""live"""
