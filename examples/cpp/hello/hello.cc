// The component's executable: CAST_COMPONENT_MAIN reads the launch contract and runs Hello.
#include "hello.h"

CAST_COMPONENT_MAIN(Hello)
