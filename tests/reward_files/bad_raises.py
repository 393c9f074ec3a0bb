def reward_function(params):
    return params['no_such_param']
