import os
import sys

# the shared MJCF snippets and helpers live in tests/models.py
sys.path.insert(0, os.path.dirname(__file__))
