"""gonio"""
