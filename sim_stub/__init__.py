"""sim_stub"""
