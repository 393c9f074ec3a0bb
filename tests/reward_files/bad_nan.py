def reward_function(params):
    return float('nan') if params['steps'] >= 3 else 1.0
