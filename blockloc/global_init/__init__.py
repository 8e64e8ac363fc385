"""global_init"""
