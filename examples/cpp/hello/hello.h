#pragma once

#include <iostream>

#include "cast/cast.h"
#include "greeting.pb.h"

// Adds greetings to its own working memory and watches them arrive.
class Hello : public cast::UnmanagedComponent {
 public:
  void configure(const cast::Args& args) override { count_ = args.getInt("count", 3); }

  void start() override {
    onChange(cast::localTypeFilter<examples::hello::Greeting>(), [this](const cast::WorkingMemoryChange& change) {
      auto greeting = get<examples::hello::Greeting>(change.id());
      std::cout << change.operation() << " " << change.id() << " (revision " << change.revision()
                << "): " << greeting.text() << std::endl;
      if (++seen_ == count_) requestStop();
    });
  }

  void run() override {
    for (int i = 0; i < count_; ++i) {
      examples::hello::Greeting greeting;
      greeting.set_text("hello " + std::to_string(i));
      greeting.set_number(i);
      add(newId(), greeting);
    }
    waitForStop();
  }

 private:
  std::int64_t count_ = 3;
  std::int64_t seen_ = 0;  // only the dispatcher thread touches it
};
