package cast.client;

/** A component that runs continuously and pushes its results to working memory. */
public abstract class UnmanagedComponent extends Component {
  @Override
  final String kind() {
    return "unmanaged";
  }
}
