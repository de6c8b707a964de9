"""rlpipe.scripts"""
